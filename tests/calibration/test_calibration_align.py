"""Band alignment: known sub-pixel shifts between bands that show the same skin with different contrast."""

from __future__ import annotations

import numpy as np
import pytest

from skinlayers.calibration.align import align_bands, apply_alignment

N = 512  # the rectified grid the pipeline aligns on
# absorbance per band of three skin structures (waves of pigment, freckles, a vein): every absorber
# darkens every band, by band-dependent amounts, so the bands differ in contrast and in which
# structure dominates
ABSORBANCE = np.array([[0.15, 0.9, 0.2], [0.1, 0.6, 0.5], [0.08, 0.4, 0.6], [0.05, 0.25, 0.3], [0.03, 0.12, 0.1]])
LEVEL = np.array([0.2, 0.3, 0.4, 0.55, 0.6])


def _structures(x, y, seed=3):
    rng = np.random.default_rng(seed)
    waves = 0.5 * (1 + np.sin(9 * x + 2) * np.cos(7 * y - 1))
    freckles = np.zeros_like(x)
    for _ in range(14):
        cx, cy = rng.uniform(-0.45, 0.45, 2)
        s = rng.uniform(0.01, 0.04)
        freckles += rng.uniform(0.3, 1) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
    vein = np.exp(-((y - 0.15 * np.sin(4 * x) - 0.1) ** 2) / (2 * 0.012**2))
    return np.stack([waves, freckles, vein])


def _bands(shifts_px, noise, seed=0):
    """Bands whose content is displaced by ``shifts_px`` (L, 2) px, with relative noise."""
    rng = np.random.default_rng(seed)
    centres = (np.arange(N) + 0.5) / N - 0.5
    out = []
    for k, (dx, dy) in enumerate(shifts_px):
        x, y = np.meshgrid(centres - dx / N, centres - dy / N)
        band = LEVEL[k] * np.exp(-np.tensordot(ABSORBANCE[k], _structures(x, y), 1))
        out.append(band * (1 + rng.normal(0, noise, band.shape)))
    return np.array(out, np.float32)


def test_known_sub_pixel_shifts_recovered_within_0_2_px():
    rng = np.random.default_rng(0)
    shifts = rng.uniform(-1.5, 1.5, (5, 2))
    shifts[2] = 0.0
    alignment = align_bands(_bands(shifts, noise=0.02), reference=2)
    errors = np.linalg.norm(alignment.shifts_px - shifts, axis=1)
    assert errors.max() <= 0.2, errors
    assert alignment.converged.all()
    assert alignment.reference == 2 and np.all(alignment.shifts_px[2] == 0)


def test_applying_the_alignment_leaves_no_shift():
    shifts = np.array([[1.3, -0.6], [0.0, 0.0], [-0.8, 1.1]])
    images = _bands(shifts, noise=0.0)[:3]
    aligned = apply_alignment(images, align_bands(images, reference=1), "cubic")
    again = align_bands(aligned, reference=1)
    assert np.abs(again.shifts_px).max() < 0.05


def test_textureless_band_fails_to_converge_and_is_reported():
    images = _bands(np.zeros((3, 2)), noise=0.0)[:3]
    images[0] = 0.3  # nothing to align on
    alignment = align_bands(images, reference=1)
    assert not alignment.converged[0] and np.isnan(alignment.shifts_px[0]).all()
    assert alignment.converged[1:].all()


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"\(L, H, W\)"):
        align_bands(np.zeros((8, 8), np.float32), 0)
    with pytest.raises(ValueError, match="reference band index 3"):
        align_bands(np.zeros((2, 8, 8), np.float32), 3)


def test_a_clipped_highlight_is_left_out_and_implausible_shifts_are_refused():
    shifts = np.array([[0.7, -0.4], [0.0, 0.0], [2.5, 0.0]])
    images = _bands(shifts, noise=0.01)[:3]
    valid = np.ones(images.shape, bool)
    images[0, 200:260, 180:240] = 5.0  # a clipped highlight in one band only
    valid[0, 200:260, 180:240] = False
    alignment = align_bands(images, reference=1, valid=valid, max_shift_px=2.0)
    assert np.linalg.norm(alignment.shifts_px[0] - shifts[0]) < 0.2
    assert not alignment.converged[2] and np.isnan(alignment.shifts_px[2]).all()  # 2.5 px > 2 px allowed
    np.testing.assert_array_equal(alignment.warps[2], np.eye(2, 3))
