"""A physical model of the window's edge in the image, fitted to the pixels along one side.

Skin lit only through the window shows, at the tape's edge, exactly half its plateau: for a homogeneous
medium lit on a half plane, what leaves at the edge is what full light would bring from the lit half.
Inward the skin brightens as the light that would have come from under the tape is missing ever less.
Pre-blur, at signed inward distance x from the edge:

    O(x) = t                                                x < 0   (tape)
    O(x) = s (1 − ½ (w e^{−x/ℓ1} + (1 − w) e^{−x/ℓ2}))        x ≥ 0   (skin)

Two exponentials describe the rise the model's renderer gives (Table 2 skin, 7.5 mm window, 430–670
nm) to within 0.5% of the plateau. The camera blurs by a Gaussian PSF σ, whose blur of
``H(x) e^{−x/ℓ}`` is ``exp(σ²/2ℓ² − x/ℓ) Φ(x/σ − σ/ℓ)``, and integrates over each pixel, whose footprint
on the side's normal is computed exactly for the side's angle. The skin level varies linearly along the
side (vignetting, texture).

Why a model: a derivative peak sits inside the true edge when the skin darkens towards it (by about
σ² × ramp slope / step height: 0.2–0.5 px on a 110-px window), and interpolating a sampled edge a
fraction of a pixel wide biases it with the pixel phase. Fitting the side's angle and offset together
with the profile removes both.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_edge_line"]

_GRID_STEP_PX = 0.04  # resolution of the model along the normal
_INSIDE_PX, _OUTSIDE_PX = 10.0, 6.0  # pixels used on either side of the edge


def fit_edge_line(img: np.ndarray, a: np.ndarray, b: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """Refit the side ``a → b`` (``(x, y)`` px; ``n`` its unit inward normal) of ``img`` ``(H, W)``.

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
    sub = (np.arange(16) + 0.5) / 16 - 0.5
    sub = np.stack(np.meshgrid(sub, sub), axis=-1).reshape(-1, 2)  # samples of one pixel's square
    half = int(np.ceil(0.75 / _GRID_STEP_PX))

    def rotated(phi: float) -> np.ndarray:
        c, s = np.cos(phi), np.sin(phi)
        return np.array([n[0] * c - n[1] * s, n[0] * s + n[1] * c])

    def blurred_rise(x, sig, ell):
        return np.exp(np.clip(sig * sig / (2 * ell * ell) - x / ell + log_ndtr(x / sig - sig / ell), -700, 50))

    def model(q):
        phi, off, tape, s0, s1, sig, w, l1, l2 = q
        nn = rotated(phi)
        footprint = np.bincount(np.round(sub @ nn / _GRID_STEP_PX).astype(int) + half, minlength=2 * half + 1)
        footprint = footprint / footprint.sum()
        step = ndtr(grid / sig)
        dark = np.convolve(1 - step, footprint, mode="same")
        rise = w * blurred_rise(grid, sig, l1) + (1 - w) * blurred_rise(grid, sig, l2)
        lit = np.convolve(step - 0.5 * rise, footprint, mode="same")
        x = p @ nn - off
        return tape * np.interp(x, grid, dark) + (s0 + s1 * along) * np.interp(x, grid, lit)

    #        angle  offset tape  skin slope  σ    w    ℓ1    ℓ2
    q0 = [0.0, 0.0, 0.0, 1.0, 0.0, 0.8, 0.7, 1.5, 8.0]
    lower = [-0.05, -3.0, -1.0, 0.2, -1.0, 0.2, 0.0, 0.05, 0.5]
    upper = [0.05, 3.0, 1.0, 5.0, 1.0, 4.0, 1.0, 30.0, 300.0]
    try:
        # lsmr: the dense SVD solver is 100× slower here when BLAS threads compete for the cores
        fit = least_squares(
            lambda q: model(q) - y, q0, bounds=(lower, upper), loss="soft_l1", f_scale=0.1, x_scale="jac",
            tr_solver="lsmr", ftol=1e-6, xtol=1e-6,
        )
    except (ValueError, np.linalg.LinAlgError):
        return None
    phi, off, sigma = float(fit.x[0]), float(fit.x[1]), float(fit.x[5])
    if not fit.success or not np.isfinite(off) or abs(off) > 2.9:
        return None
    nn = rotated(phi)
    return nn, float((mid @ nn) + off), sigma
