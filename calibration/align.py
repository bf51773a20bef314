"""Band-to-band alignment of the rectified window images.

Every band's window is cut out of its own frame, so the bands already agree up to the error of the
corners (a small fraction of a cube pixel); what is left is found by maximising the enhanced
correlation coefficient (ECC; Evangelidis & Psarakis 2008, OpenCV ``findTransformECC``) between each band
and a reference band in the middle of the spectrum. Across bands of different contrast ECC itself errs
by more than that, so the pipeline applies only shifts beyond ``align_min_shift_px`` — skin that slid
under the tape — and reports the others (both errors: docs/calibration.md, "From calibration/align.py").

Skin differs in contrast from band to band (melanin and blood dominate the blue, little shows in the
red), so the images compared are gradients of the Gaussian-smoothed bands — the two components
(∂x, ∂y) as channels of one image, not the gradient magnitude. A band is close to a mixture of the same
structures with band-dependent weights (absorbers darken every band, by different amounts); gradients
are linear in that mixture, so each structure pulls towards the same shift, while the magnitude mixes
overlapping structures non-linearly and biased the shift more than the components did
(docs/calibration.md, "From calibration/align.py"). ECC is invariant to the bands' gain and offset.

The skin darkens towards the tape, a pattern that belongs to the window, not to the skin: skin that
slid under the tape would be pulled back towards zero shift by it. Each band is therefore divided by a
smooth profile of the distance to the window edge (``flatten_edge_profile``), which gives back nearly
the whole slide, and a thin border along the edge is left out (a synthetic test of both:
docs/calibration.md, "From calibration/align.py").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

__all__ = ["Alignment", "align_bands", "apply_alignment", "flatten_edge_profile", "gradient_field"]

_MOTION = {"translation": cv2.MOTION_TRANSLATION, "euclidean": cv2.MOTION_EUCLIDEAN}
_INTERPOLATION = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "lanczos": cv2.INTER_LANCZOS4}


@dataclass(frozen=True)
class Alignment:
    """ECC warps ``(L, 2, 3)`` mapping reference-band pixels to each band's pixels; ``shifts_px``
    ``(L, 2)``: (dx, dy) of each band's content relative to the reference (its warp's translation, px of
    the aligned images; NaN where ECC failed); ``rotation_deg`` ``(L,)``; ``correlation`` ``(L,)``: the
    final ECC; ``converged`` ``(L,)``; ``reference``: index of the reference band."""

    warps: np.ndarray
    shifts_px: np.ndarray
    rotation_deg: np.ndarray
    correlation: np.ndarray
    converged: np.ndarray
    reference: int


def flatten_edge_profile(image: np.ndarray) -> np.ndarray:
    """``image`` ``(H, W)`` divided by a smooth profile of the distance e to the nearest edge: the means
    over square rings of equal e, fitted (robustly, so texture leaves no rings) with
    ``a + b e^{−e/ℓ1} + c e^{−e/ℓ2}``, the darkening's shape near the tape."""
    from scipy.optimize import least_squares  # noqa: PLC0415

    image = np.asarray(image, np.float32)
    h, w = image.shape
    ys, xs = np.mgrid[0:h, 0:w]
    ring = np.minimum(np.minimum(xs, w - 1 - xs), np.minimum(ys, h - 1 - ys)).ravel()
    means = np.bincount(ring, weights=image.ravel().astype(np.float64)) / np.maximum(np.bincount(ring), 1)
    e = np.arange(means.size, dtype=np.float64)
    scale = float(np.median(means))
    if not scale > 0:
        return image

    def profile(q):
        return q[0] + q[1] * np.exp(-e / q[3]) + q[2] * np.exp(-e / q[4])

    fit = least_squares(
        lambda q: profile(q) - means / scale, [1.0, -0.3, -0.2, 3.0, 30.0],
        bounds=([0, -2, -2, 0.3, 3.0], [5, 2, 2, 30.0, 1e4]), loss="soft_l1", f_scale=0.02, tr_solver="lsmr",
    )
    level = (profile(fit.x) * scale)[ring].reshape(h, w)
    return np.divide(image, level, out=np.ones_like(image), where=level > 0).astype(np.float32)


def gradient_field(image: np.ndarray, sigma_px: float = 3.0) -> np.ndarray:
    """∇(G_σ ∗ image) as a 3-channel image ``(H, W, 3)`` float32: ∂x, ∂y (Scharr) and a zero channel
    (OpenCV's ECC takes one or three channels)."""
    smooth = cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), sigma_px)
    gx = cv2.Scharr(smooth, cv2.CV_32F, 1, 0)
    gy = cv2.Scharr(smooth, cv2.CV_32F, 0, 1)
    return np.dstack([gx, gy, np.zeros_like(gx)])


def align_bands(
    images: np.ndarray,
    reference: int,
    *,
    valid: np.ndarray | None = None,
    motion: Literal["translation", "euclidean"] = "translation",
    border: float = 0.06,
    max_shift_px: float = float("inf"),
    sigma_px: float = 3.0,
    iterations: int = 100,
) -> Alignment:
    """Align each band of ``images`` ``(L, H, W)`` (rectified windows) to band ``reference`` by ECC on the
    gradient fields of the bands flattened by their edge profile.

    ``valid`` ``(L, H, W)`` bool: pixels to trust (saturated or under-exposed ones are filled with the
    band's median and, with their surround, left out of the comparison, so a clipped highlight cannot
    drag a band away). ``border``: fraction of each side along the edge left out. A band where ECC does
    not converge, or finds a shift beyond ``max_shift_px``, gets the identity warp, NaN shifts and
    ``converged`` False.
    """
    images = np.asarray(images, np.float32)
    if images.ndim != 3:
        raise ValueError(f"align_bands needs images (L, H, W), got shape {images.shape}")
    n, h, w = images.shape
    if not 0 <= reference < n:
        raise ValueError(f"reference band index {reference} outside 0…{n - 1}")
    valid = np.ones(images.shape, bool) if valid is None else np.asarray(valid, bool)
    if valid.shape != images.shape:
        raise ValueError(f"valid has shape {valid.shape}, the images {images.shape}")
    reach = int(np.ceil(3 * sigma_px)) * 2 + 1
    trusted = [cv2.erode(v.astype(np.uint8), np.ones((reach, reach), np.uint8)) for v in valid]
    filled = [np.where(v, im, np.median(im[v]) if v.any() else 0.0).astype(np.float32) for im, v in zip(images, valid)]
    grads = [gradient_field(flatten_edge_profile(im), sigma_px) for im in filled]
    inner = np.zeros((h, w), np.uint8)
    by, bx = int(round(border * h)), int(round(border * w))
    inner[by : h - by, bx : w - bx] = 1
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-6)
    warps = np.tile(np.eye(2, 3, dtype=np.float32), (n, 1, 1))
    correlation = np.ones(n)
    converged = np.ones(n, bool)
    for k in range(n):
        if k == reference:
            continue
        mask = inner & trusted[k] & trusted[reference]
        try:
            cc, warp = cv2.findTransformECC(grads[reference], grads[k], warps[k].copy(), _MOTION[motion], criteria, mask, 3)
        except cv2.error:
            converged[k], correlation[k] = False, np.nan
            continue
        if not np.hypot(*warp[:, 2]) <= max_shift_px:
            converged[k], correlation[k] = False, cc
            continue
        warps[k], correlation[k] = warp, cc
    shifts = warps[:, :, 2].astype(np.float64)
    shifts[~converged] = np.nan
    rotation = np.degrees(np.arctan2(warps[:, 1, 0], warps[:, 0, 0])).astype(np.float64)
    return Alignment(
        warps=warps, shifts_px=shifts, rotation_deg=rotation, correlation=correlation, converged=converged, reference=reference
    )


def apply_alignment(
    images: np.ndarray, alignment: Alignment, interpolation: Literal["linear", "cubic", "lanczos"] = "cubic"
) -> np.ndarray:
    """Resample every band of ``images`` ``(L, H, W)`` onto the reference band's pixels."""
    images = np.asarray(images, np.float32)
    h, w = images.shape[1:]
    out = np.empty_like(images)
    for k, im in enumerate(images):
        out[k] = cv2.warpAffine(
            im, alignment.warps[k], (w, h), flags=_INTERPOLATION[interpolation] | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
        )
    return out
