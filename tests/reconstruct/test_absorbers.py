"""The grey interface absorbance the fit can add where the residual asks (``absorbers: auto``,
``reconstruct/diagnosis/absorbers.py``): it lands on the hairs, nowhere it is not asked for, and reaches the maps
file. (Off by default: on the demo's scene it has not yet made the maps better, docs/reconstruct.md.)"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from skinlayers.model.patch.maps_io import read_maps
from skinlayers.reconstruct.mapfit.fit import fit_cube
from skinlayers.reconstruct.results.outputs import fit_summary, write_outputs
from skinlayers.reconstruct.settings import FitSettings

SETTINGS = FitSettings(max_iterations=15, map_cell_mm={"C_bc": 0.0}, absorbers="auto")


@pytest.fixture(scope="module")
def hairy(synthetic):
    syn = synthetic.make_cube(24, seed=4, preset="IV exterior", hairs=4, noise=0.25, blur="pyramid")
    return syn, fit_cube(syn.cube, SETTINGS)


def test_the_absorbance_lands_on_the_hairs(hairy):
    syn, fit = hairy
    found = fit.absorbers
    assert found["kept"] > 0 and found["chi2_after"] < found["chi2_before"], found
    p = fit.maps.absorbance[0, 0]
    near_hair = F.max_pool2d(syn.hair[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    near_vein = F.max_pool2d(syn.vein[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    kept = p > 0
    assert float((near_hair | near_vein)[kept].float().mean()) > 0.8  # where the model lacks an absorber
    assert float(p[syn.hair].mean()) > 5.0 * float(p[~(near_hair | near_vein)].mean()) + 1e-6
    assert found["kept"] == int(kept.sum())


def test_the_absorbance_and_its_evidence_reach_the_outputs(hairy, tmp_path):
    _, fit = hairy
    summary = fit_summary(fit, SETTINGS)
    assert summary["absorbers"]["kept"] == fit.absorbers["kept"] and "ln n" in summary["absorbers"]["reason"]
    write_outputs(fit, SETTINGS, tmp_path)
    maps = read_maps(tmp_path / "maps.exr")
    assert maps.absorbance is not None and maps.absorbance.shape[1] == fit.wavelength_nm.numel()
    assert torch.allclose(maps.absorbance[0, 0], fit.maps.absorbance[0, 0].float())


def test_nothing_is_added_to_a_patch_the_model_holds(synthetic):
    """Flat skin at the camera's noise: no pixel's residual stands out enough, or none keeps its P."""
    syn = synthetic.make_cube(24, seed=6, features=False, variation=0.0, noise=0.25, blur="pyramid")
    fit = fit_cube(syn.cube, SETTINGS.model_copy(update={"forward": "heterogeneous"}))
    assert fit.absorbers["kept"] <= 0.01 * syn.cube.mask.sum(), fit.absorbers
    assert fit.maps.absorbance is None or float(fit.maps.absorbance.max()) < 0.05
