"""Sums of Gaussians for radial profiles (d'Eon et al. 2007; DWRR08 §4.3, Eq. 4 and 9).

G(v; r) = exp(-r²/2v) / (2πv) integrates to one over the plane; its 2D Fourier transform is
exp(-v k²/2). A profile P(r) ≈ Σ w_k G(v_k; r) with v_k = v_0 2^k and w_k ≥ 0, fitted by non-negative
least squares in the plane (weight r dr) with the constraint Σ w_k = ∫P, so that the sum carries
exactly the profile's energy.

Shapes: weights ``(..., K)``, variances ``(K,)``, radii or frequencies ``(N,)`` → ``(..., N)``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.optimize import nnls

__all__ = ["fit_gaussian_weights", "gaussian_sum_hankel", "gaussian_sum_profile", "plane_quadrature"]


def gaussian_sum_profile(weights: torch.Tensor, variances_mm2: torch.Tensor, r_mm: torch.Tensor) -> torch.Tensor:
    """Σ_k w_k G(v_k; r), mm⁻², ``(..., N)``."""
    v = variances_mm2.to(weights)
    g = torch.exp(-r_mm.to(weights)[:, None] ** 2 / (2.0 * v)) / (2.0 * math.pi * v)
    return weights @ g.T


def gaussian_sum_hankel(weights: torch.Tensor, variances_mm2: torch.Tensor, k_per_mm: torch.Tensor) -> torch.Tensor:
    """2D Fourier transform of ``gaussian_sum_profile``: Σ_k w_k exp(-v_k k²/2), ``(..., N)``."""
    v = variances_mm2.to(weights)
    return weights @ torch.exp(-0.5 * k_per_mm.to(weights)[:, None] ** 2 * v).T


def plane_quadrature(r_min_mm: float, r_max_mm: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Log-spaced radii and the weights of ∫ f(r) 2πr dr on them (trapezoid in log r)."""
    u = np.linspace(math.log(r_min_mm), math.log(r_max_mm), n)
    r = np.exp(u)
    du = np.gradient(u)
    du[0] *= 0.5
    du[-1] *= 0.5
    return r, 2.0 * math.pi * r * r * du


def fit_gaussian_weights(
    profiles: np.ndarray,
    totals: np.ndarray,
    variances_mm2: np.ndarray,
    r_mm: np.ndarray,
    quad_weights: np.ndarray,
    energy_weight: float = 10.0,
) -> np.ndarray:
    """Non-negative weights ``(B, K)`` of Gaussians fitting ``profiles`` ``(B, N)`` sampled at ``r_mm``.

    Minimises the plane L2 error Σ_j q_j (P_j - Σ_k w_k G_k(r_j))² with a heavily weighted row that
    asks Σ w = total, then rescales so that Σ w equals the profile's exact ``totals`` ``(B,)``
    (the closed-form plane integral), keeping every weight ≥ 0. A zero total gives zero weights.
    """
    profiles = np.asarray(profiles, dtype=np.float64)
    totals = np.asarray(totals, dtype=np.float64)
    v = np.asarray(variances_mm2, dtype=np.float64)
    sqrt_q = np.sqrt(quad_weights)
    basis = sqrt_q[:, None] * np.exp(-(r_mm[:, None] ** 2) / (2.0 * v)) / (2.0 * math.pi * v)
    out = np.zeros((profiles.shape[0], v.size))
    for i, (profile, total) in enumerate(zip(profiles, totals)):
        if not total > 0.0:
            continue
        target = sqrt_q * profile / total
        mu = energy_weight * max(np.linalg.norm(target), 1.0)
        system = np.vstack([basis, np.full((1, v.size), mu)])
        rhs = np.concatenate([target, [mu]])
        w, _ = nnls(system, rhs, maxiter=50 * v.size)
        s = w.sum()
        out[i] = w * (total / s) if s > 0 else 0.0
    return out
