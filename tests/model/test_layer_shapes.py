"""The transport shapes (model/column/layer_shapes.py): the shipped tables against fresh walks of the project's
Monte Carlo, their closed-form unscattered part against the walk's, and the line-spread fit against
a Gaussian mixture whose weights are known."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.special import erf

from skinlayers.model import ModelSettings
from skinlayers.model.column import layer_shapes as ls
from skinlayers.model.transport import Medium, walk

F64 = torch.float64
#: Offsets (units of 1/σt′) at which the share of light beyond is compared.
XI_CHECK = (0.1, 0.3, 1.0, 3.0, 10.0)


def _beyond(shares: np.ndarray, xi: float) -> float:
    """Share of the line spread beyond ``xi`` (at a bin edge at or below it)."""
    edges = ls.shape_edges()
    b = int(np.searchsorted(edges, xi, side="right")) - 1
    return float(shares[b:].sum() / shares.sum())


def _node_index(nodes: np.ndarray, value: float) -> int:
    return int(np.argmin(np.abs(nodes - value)))


@pytest.mark.parametrize("x", [-1.5, 0.0])
def test_shipped_half_space_shape_is_what_the_walk_makes(x):
    photons = 40_000
    top, _ = ls._walk(x, math.inf, True, photons, 77, ls.N_DERMIS, ls.N_EPIDERMIS, ls.N_EPIDERMIS, refract_from=ls.N_EPIDERMIS)
    shipped = ls._tables()["half"][_node_index(ls.HALF_SPACE_X, x)]
    np.testing.assert_allclose(ls.half_space_shape(np.array([x]))[0], shipped)
    for xi in XI_CHECK:
        p = _beyond(shipped, xi)
        se = math.sqrt(max(p * (1 - p), 1e-4) / photons)
        assert abs(_beyond(top, xi) - p) < 5 * se + 2e-3, (x, xi, _beyond(top, xi), p)


def test_shipped_slab_shapes_are_what_the_walk_makes():
    x, y, photons = -1.0, 0.25, 40_000
    tau = 10.0**y * (1.0 + 10.0**x)
    r_plus, t_plus = ls._walk(x, tau, False, photons, 78, ls.N_EPIDERMIS, ls.N_ABOVE, ls.N_EPIDERMIS)
    r_minus, t_minus = ls._walk(x, tau, True, photons, 79, ls.N_EPIDERMIS, ls.N_EPIDERMIS, ls.N_ABOVE)
    t_direct, r_direct = ls._unscattered(tau, 1.0 / (1.0 + 10.0**x))
    shipped = ls.slab_shapes(np.array([x]), y)[:, 0]
    for p, walked in enumerate((r_plus, t_plus, r_minus + r_direct, t_minus + t_direct)):
        for xi in XI_CHECK:
            q = _beyond(shipped[p], xi)
            se = math.sqrt(max(q * (1 - q), 1e-4) / photons)
            assert abs(_beyond(walked, xi) - q) < 5 * se + 2e-3, (ls.SLAB_PROFILES[p], xi, _beyond(walked, xi), q)


def test_unscattered_part_matches_the_walks_totals():
    """Lambertian light from below a slab: what crosses it without scattering, transmitted into air
    and reflected back out below, closed form against the walk's unscattered tallies."""
    x, tau, photons = 0.0, 0.3, 200_000
    ratio = 10.0**x
    cols = 2001
    medium = Medium((tau,), (ls.N_EPIDERMIS,), ls.N_EPIDERMIS, ls.N_ABOVE, (1 / (1 + ratio),), 0.0,
                    torch.full((1, 1, cols), ratio / (1 + ratio), dtype=F64), torch.ones(0, 1, cols, dtype=F64), 0.01)
    g = torch.Generator().manual_seed(4)
    cos = torch.sqrt(torch.rand(photons, dtype=F64, generator=g)).clamp_min(1e-9)
    tally = walk(medium, torch.zeros(photons, dtype=F64), torch.zeros(photons, dtype=F64), cos, torch.ones(photons, dtype=F64), g,
                 across_y=True, azimuth=2 * math.pi * torch.rand(photons, dtype=F64, generator=g))
    t_direct, r_direct = ls._unscattered(tau, 1 / (1 + ratio))
    for closed, walked in ((t_direct.sum(), float(tally.unscattered_transmitted[0]) / photons),
                           (r_direct.sum(), float(tally.unscattered_reflected[0]) / photons)):
        se = math.sqrt(walked * (1 - walked) / photons)
        assert abs(closed - walked) < 5 * se, (closed, walked)


def test_the_walks_bottom_tally_holds_its_transmitted_light():
    tau, photons, cols = 1.0, 20_000, 4001
    medium = Medium((tau,), (1.4,), 1.0, 1.4, (0.9,), 0.0, torch.full((1, 1, cols), 0.1, dtype=F64), torch.ones(0, 1, cols, dtype=F64), 0.01)
    g = torch.Generator().manual_seed(5)
    tally = walk(medium, torch.zeros(photons, dtype=F64), torch.zeros(photons, dtype=F64), torch.ones(photons, dtype=F64),
                 torch.ones(photons, dtype=F64), g, across_y=True, tally_bottom=True)
    assert float(tally.transmitted[0]) > 0.2 * photons
    torch.testing.assert_close(tally.bottom.sum(), tally.transmitted[0], rtol=1e-3, atol=0)  # within ±20 mfp: all of it
    with pytest.raises(ValueError, match="finite stack"):
        walk(Medium((math.inf,), (1.4,), 1.0, 1.0, (1.0,), 0.0, torch.ones(1, 1, 3, dtype=F64), torch.ones(0, 1, 3, dtype=F64), 0.1),
             torch.zeros(1, dtype=F64), torch.zeros(1, dtype=F64), torch.ones(1, dtype=F64), torch.ones(1, dtype=F64), g, tally_bottom=True)


def test_line_spread_fit_recovers_a_known_mixture():
    """Shares made from three of the basis's Gaussians are fitted back: the same line spread (every
    bin's share within 1% of the largest) and Σ w the total asked for."""
    variances = np.array(ModelSettings().tables.gaussian_variances_mm2())
    truth = np.zeros(variances.size)
    truth[[3, 9, 15]] = (0.2, 0.5, 0.3)
    sigma_t = np.array([5.0])
    bound = erf(ls.shape_edges()[:, None] / sigma_t[0] / np.sqrt(2 * variances)[None, :])
    shares = ((bound[1:] - bound[:-1]) @ truth)[None]
    w = ls.fit_line_spread_weights(shares, sigma_t, np.array([0.37]), variances)
    assert w.sum() == pytest.approx(0.37, rel=1e-12) and (w >= 0).all()
    fitted = (bound[1:] - bound[:-1]) @ (w[0] / 0.37)
    assert np.abs(fitted - shares[0]).max() < 0.01 * shares.max()
    for xi in XI_CHECK:
        assert abs(_beyond(fitted, xi) - _beyond(shares[0], xi)) < 1e-3
