"""Damaged cubes: a dead band, a saturated region, hair. The fit completes, flags the pixels and says
so in fit.json; cubes it cannot use are refused with one clear message."""

from __future__ import annotations

import json

import pytest
import torch

from skinlayers.formats.cube import Cube
from skinlayers.model import PARAMETER_NAMES
from skinlayers.reconstruct.diagnosis.checks import FLAG_BITS
from skinlayers.reconstruct.mapfit.fit import fit_cube
from skinlayers.reconstruct.results.outputs import fit_summary
from skinlayers.reconstruct.settings import FitSettings

# carotene per pixel, as for the small cube of the same noise (conftest.SMALL_FIT)
FAST = FitSettings(max_iterations=15, map_cell_mm={"C_bc": 0.0})


def _flag(fit, name):
    return ((fit.flags >> FLAG_BITS[name]) & 1).bool()


def _damaged(cube: Cube, reflectance: torch.Tensor, mask: torch.Tensor | None = None) -> Cube:
    return Cube(reflectance, cube.mask if mask is None else mask, cube.header)


@pytest.fixture(scope="module")
def damaged(synthetic):
    """One cube with all three kinds of damage: hairs, a dead band (520 nm came out black) and a
    clipped highlight (every band at 1.0, not masked by the cube); fitted once."""
    syn = synthetic.make_cube(24, seed=4, preset="IV exterior", hairs=4, noise=0.25, blur="pyramid")
    refl = syn.cube.reflectance.clone()
    refl[3] = 0.0
    refl[:, 16:20, 3:7] = 1.0
    fit = fit_cube(_damaged(syn.cube, refl), FAST)
    return syn, fit, fit_summary(fit, FAST)


def test_dead_band_is_left_out_and_reported(damaged):
    syn, fit, summary = damaged
    assert [b["wavelength_nm"] for b in summary["data_checks"]["excluded_bands"]] == [520.0]
    assert any("520" in note for note in summary["data_checks"]["notes"])
    assert not summary["residual"]["per_band"]["520"]["used"]
    assert summary["flags"]["counts"]["band_excluded"] == 24 * 24
    assert bool(_flag(fit, "band_excluded").all())
    # the other eight bands still determine the maps
    keep = syn.cube.mask & ~syn.vein & ~syn.hair & ~_flag(fit, "masked")
    err = ((fit.maps.C_m[0] - syn.truth.C_m[0]).abs() / syn.truth.C_m[0])[keep].median()
    assert float(err) < 0.15
    assert all(bool(torch.isfinite(getattr(fit.maps, n)).all()) for n in PARAMETER_NAMES)


def test_saturated_region_is_masked_flagged_and_followed(damaged):
    syn, fit, summary = damaged
    sat = _flag(fit, "saturated")
    assert int(sat.sum()) == 16 and bool(sat[16:20, 3:7].all())
    assert bool(_flag(fit, "masked")[16:20, 3:7].all())
    assert summary["data_checks"]["saturated_pixels"] == 16
    assert summary["flags"]["counts"]["saturated"] == 16
    assert any("saturated" in note for note in summary["data_checks"]["notes"])
    # its parameters are copies of visible pixels' (the nearest), not values of their own
    visible = ~_flag(fit, "masked")
    inside = fit.maps.C_m[0, 16:20, 3:7].reshape(-1).tolist()
    assert set(inside) <= set(fit.maps.C_m[0][visible].tolist())
    assert bool(torch.isnan(fit.sigma[:, 16:20, 3:7]).all())


def test_hair_and_vein_are_fitted_and_flagged_by_their_residual(damaged):
    syn, fit, summary = damaged
    hair = syn.hair & ~_flag(fit, "masked")
    assert int(hair.sum()) > 5
    high = _flag(fit, "high_residual")
    assert float(high[hair].float().mean()) > 0.6, float(high[hair].float().mean())
    # the other flagged pixels are the vein (left to the residual, as in the paper) and hairs' neighbours
    near_hair = torch.nn.functional.max_pool2d(syn.hair[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    explained = (near_hair | syn.vein)[high]
    assert float(explained.float().mean()) > 0.9, float(explained.float().mean())
    clean = ~near_hair & ~syn.vein & ~_flag(fit, "masked")
    assert float(high[clean].float().mean()) < 0.02
    assert summary["flags"]["counts"]["high_residual"] == int(high.sum())
    assert json.dumps(summary, allow_nan=True)


def test_cube_with_too_few_usable_bands_is_refused(small_cube):
    refl = small_cube.cube.reflectance.clone()
    refl[:4] = 0.0
    with pytest.raises(ValueError, match="usable band"):
        fit_cube(_damaged(small_cube.cube, refl), FAST)


def test_empty_mask_is_refused(small_cube):
    mask = torch.zeros_like(small_cube.cube.mask)
    with pytest.raises(ValueError, match="no usable pixel"):
        fit_cube(_damaged(small_cube.cube, small_cube.cube.reflectance, mask), FAST)


def test_a_band_read_dark_is_reported_not_fitted_silently(small_cube, small_fit, small_fit_settings):
    """A green band 8% too dark (a wrong Spectralon value at that band): no maps match it, and the fit
    says so, naming that band first, in the notes and in fit.json; the clean cube raises nothing."""
    from skinlayers.reconstruct.diagnosis.checks import BAND_BIAS_LIMIT

    wl = small_cube.cube.wavelength_nm.tolist()
    j = wl.index(550.0)
    assert all(abs(b) < BAND_BIAS_LIMIT / 4 for b in small_fit.band_bias.values()), small_fit.band_bias
    assert not any("stay off the best fit" in n for n in small_fit.checks.notes)
    r = small_cube.cube.reflectance.clone()
    r[j] *= 0.92
    fit = fit_cube(Cube(r, small_cube.cube.mask, small_cube.cube.header), FitSettings(**small_fit_settings))
    notes = [n for n in fit.checks.notes if "stay off the best fit" in n]
    assert len(notes) == 1 and "550 nm" in notes[0] and "calibration of 550 nm first" in notes[0], fit.checks.notes
    assert fit.band_bias["550"] > BAND_BIAS_LIMIT
    summary = fit_summary(fit, FitSettings(**small_fit_settings))
    assert summary["data_checks"]["band_bias"]["550"] > BAND_BIAS_LIMIT and notes[0] in summary["data_checks"]["notes"]
