"""Sums of Gaussians (DWRR08 §3, Eq. 4; §4.3, Eq. 9; §4.5; after d'Eon et al. 2007): the non-negative
fit and the closed-form transforms.

References: exact sums of the basis Gaussians (the fit must give their weights back), the Gaussian's
unit plane integral and its 2D Fourier transform exp(-v k²/2), both checked by numerical integrals
written here (trapezoid in ln r, J0 from scipy), not by the module's own quadrature helper.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate
from scipy.special import j0

from skinlayers.model import TableSettings, fit_gaussian_weights, gaussian_sum_hankel, gaussian_sum_profile

F64 = torch.float64
VARIANCES = np.array(TableSettings().gaussian_variances_mm2())  # the tables' own basis: 21 Gaussians
K = VARIANCES.size


def fit_grid(r_min: float = 2e-4, r_max: float = 80.0, n: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Log-spaced radii and trapezoid-in-ln-r weights of ∫ f 2πr dr (built here, independently)."""
    u = np.linspace(math.log(r_min), math.log(r_max), n)
    r = np.exp(u)
    q = np.full(n, u[1] - u[0]) * 2.0 * math.pi * r * r
    q[[0, -1]] *= 0.5
    return r, q


def basis(r: np.ndarray) -> np.ndarray:
    """G(v_k; r) = exp(-r²/2v)/(2πv), ``(K, N)``."""
    return np.exp(-(r[None, :] ** 2) / (2.0 * VARIANCES[:, None])) / (2.0 * math.pi * VARIANCES[:, None])


@pytest.fixture(scope="module")
def exact_sums() -> tuple[np.ndarray, np.ndarray]:
    """40 weight vectors: random non-negative with about half the entries zero, single Gaussians at
    both ends of the basis, and a smooth bump; profiles sampled on the fit grid."""
    rng = np.random.default_rng(20080808)
    w = rng.uniform(0.0, 1.0, (40, K)) * (rng.uniform(size=(40, K)) < 0.5)
    w[0] = 0.0
    w[0, 0] = 1.0
    w[1] = 0.0
    w[1, -1] = 0.3
    w[2] = np.exp(-0.5 * ((np.arange(K) - 9.0) / 2.0) ** 2)
    w[3] = 0.0
    w[3, 5] = 2e-9  # a faint profile: the fit works on the shape, so scale does not matter
    r, _ = fit_grid()
    return w, w @ basis(r)


def test_fit_recovers_exact_basis_weights(exact_sums):
    """Measured: recovered to 1e-14 of the largest weight; asserted 1e-8."""
    w_true, profiles = exact_sums
    r, q = fit_grid()
    w = fit_gaussian_weights(profiles, w_true.sum(1), VARIANCES, r, q)
    err = np.abs(w - w_true).max(1) / w_true.max(1)
    assert err.max() < 1e-8, f"worst weight error {err.max():.2e} of the largest weight (row {err.argmax()})"


def test_fit_weights_non_negative_and_sum_to_the_given_total(exact_sums):
    """Σw must equal the given total (the closed-form energy) even where it disagrees with the samples:
    here the totals are deliberately off by -30 % … +30 %."""
    w_true, profiles = exact_sums
    r, q = fit_grid()
    rng = np.random.default_rng(7)
    totals = w_true.sum(1) * rng.uniform(0.7, 1.3, w_true.shape[0])
    w = fit_gaussian_weights(profiles, totals, VARIANCES, r, q)
    assert (w >= 0.0).all()
    np.testing.assert_allclose(w.sum(1), totals, rtol=1e-13, atol=0)


def test_fit_of_a_non_gaussian_profile_keeps_weights_non_negative():
    """An exponential-tailed profile (like a diffusion profile) cannot be matched exactly: the weights
    must still be ≥ 0 and sum to the total."""
    r, q = fit_grid()
    profiles = np.stack([np.exp(-r / s) / (2.0 * math.pi * s * s) for s in (0.01, 0.1, 1.0)])
    w = fit_gaussian_weights(profiles, np.ones(3), VARIANCES, r, q)
    assert (w >= 0.0).all()
    np.testing.assert_allclose(w.sum(1), 1.0, rtol=1e-13)


def test_zero_total_gives_zero_weights():
    r, q = fit_grid()
    profiles = np.stack([np.zeros_like(r), basis(r)[4]])
    w = fit_gaussian_weights(profiles, np.array([0.0, 1.0]), VARIANCES, r, q)
    assert (w[0] == 0.0).all()
    assert w[1].sum() == pytest.approx(1.0, rel=1e-13)


def test_gaussian_sum_profile_matches_direct_sum_and_integrates_to_total(exact_sums):
    w_true, profiles = exact_sums
    r, _ = fit_grid()
    module = gaussian_sum_profile(torch.from_numpy(w_true), torch.from_numpy(VARIANCES), torch.from_numpy(r))
    np.testing.assert_allclose(module.numpy(), profiles, rtol=1e-12, atol=0)
    u = np.linspace(math.log(1e-9), math.log(1e3), 6000)
    rr = np.exp(u)
    g = gaussian_sum_profile(torch.from_numpy(w_true), torch.from_numpy(VARIANCES), torch.from_numpy(rr)).numpy()
    energy = np.trapezoid(g * 2.0 * math.pi * rr * rr, u, axis=-1)
    np.testing.assert_allclose(energy, w_true.sum(1), rtol=1e-10)


def test_gaussian_sum_hankel_at_zero_is_total(exact_sums):
    w_true, _ = exact_sums
    closed = gaussian_sum_hankel(torch.from_numpy(w_true), torch.from_numpy(VARIANCES), torch.zeros(1, dtype=F64))
    np.testing.assert_allclose(closed[:, 0].numpy(), w_true.sum(1), rtol=1e-14)


def test_gaussian_sum_hankel_matches_numerical_transform():
    """Each basis Gaussian (weights = identity, so every column of the transform is tested) against
    2π ∫ G(r) J0(kr) r dr by Simpson in ln r on r ∈ √v·[1e-6, 40], at k√v ∈ {0.1, 0.5, 1, 2, 3.5}
    (transforms down to e^-6); worst absolute error asserted below 1e-9."""
    v = torch.from_numpy(VARIANCES)
    x = np.linspace(math.log(1e-6), math.log(40.0), 20000)
    for j, var in enumerate(VARIANCES):
        std = math.sqrt(var)
        k = torch.tensor([0.1, 0.5, 1.0, 2.0, 3.5], dtype=F64) / std
        r = std * np.exp(x)
        weights = torch.zeros(1, K, dtype=F64)
        weights[0, j] = 1.0
        closed = gaussian_sum_hankel(weights, v, k)[0].numpy()
        g = gaussian_sum_profile(weights, v, torch.from_numpy(r))[0].numpy()
        numeric = integrate.simpson(g * j0(np.outer(k.numpy(), r)) * 2.0 * math.pi * r * r, x=x, axis=-1)
        assert np.abs(numeric - closed).max() < 1e-9, (j, numeric, closed)


def test_shapes_and_dtype():
    w = torch.rand(3, 2, K, dtype=F64)
    v = torch.from_numpy(VARIANCES)
    r = torch.linspace(0.0, 5.0, 7, dtype=F64)
    assert gaussian_sum_profile(w, v, r).shape == (3, 2, 7)
    assert gaussian_sum_hankel(w, v, r).shape == (3, 2, 7)
    w32 = w.float()
    assert gaussian_sum_hankel(w32, v, r).dtype == torch.float32
    torch.testing.assert_close(gaussian_sum_hankel(w32, v, r).double(), gaussian_sum_hankel(w, v, r), rtol=1e-5, atol=0)


def test_gradcheck_gaussian_sums():
    w = torch.rand(2, K, dtype=F64, requires_grad=True)
    v = torch.from_numpy(VARIANCES)
    r = torch.tensor([0.0, 0.01, 0.1, 1.0], dtype=F64)
    assert torch.autograd.gradcheck(lambda x: gaussian_sum_profile(x, v, r), (w,))
    assert torch.autograd.gradcheck(lambda x: gaussian_sum_hankel(x, v, r), (w,))
