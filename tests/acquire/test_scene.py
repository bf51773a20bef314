"""Synthetic scenes: deterministic for a seed, the same scene on any grid, each feature where and what
it should be, and clear errors for bad files."""

from __future__ import annotations

import math

import pytest
import torch

from skinlayers.acquire.simulator.scene import SceneConfig, SceneError, SkinScene, load_scene, scene_from_dict
from skinlayers.model.optics.params import PARAMETER_NAMES, TABLE2
from skinlayers.model.optics.spectra import chromophore_spectra

WL = torch.tensor([450.0, 550.0, 650.0], dtype=torch.float64)
CHANNELS = (*PARAMETER_NAMES,)


def _maps(scene: SkinScene, mm: float = 0.06, n: int = 150):
    return scene.maps(mm, n, WL)


def test_embedded_default_is_the_shipped_yaml():
    assert load_scene() == SceneConfig()


def test_same_seed_same_maps_other_seed_other_maps():
    a, b, c = (_maps(SkinScene(None, s)) for s in (7, 7, 8))
    for n in CHANNELS:
        assert torch.equal(getattr(a, n), getattr(b, n)), n
    assert torch.equal(a.absorbance, b.absorbance)
    assert not torch.equal(a.C_m, c.C_m)
    assert not torch.equal(a.absorbance, c.absorbance)


def test_a_finer_grid_renders_the_same_scene():
    """Pixel centres of a grid 3× finer fall on every coarse centre: the values there must agree."""
    scene = SkinScene(None, 3)
    coarse, fine = scene.maps(0.09, 100, WL), scene.maps(0.03, 300, WL)
    for n in CHANNELS:
        torch.testing.assert_close(getattr(fine, n)[:, 1::3, 1::3], getattr(coarse, n), rtol=1e-6, atol=0)
    torch.testing.assert_close(fine.absorbance[..., 1::3, 1::3], coarse.absorbance, rtol=1e-6, atol=1e-7)


def test_base_skin_with_no_features_is_the_table2_row():
    cfg = scene_from_dict({"base": {"preset": "V exterior"}, "variation": {"C_m": 0, "beta_m": 0, "C_he": 0, "C_bc": 0, "C_hd": 0},
                           "freckles": {"count": 0}, "scar": {"count": 0}, "veins": {"count": 0}, "hairs": {"count": 0}})
    maps = _maps(SkinScene(cfg, 0), n=20)
    for n in CHANNELS:
        torch.testing.assert_close(getattr(maps, n), torch.full_like(maps.C_m, TABLE2["V exterior"][n]))
    assert float(maps.absorbance.abs().max()) == 0.0


def test_explicit_values_override_the_preset_and_need_all_five_without_one():
    cfg = scene_from_dict({"base": {"preset": "I interior", "C_m": 0.02}, "variation": {"C_m": 0}, "freckles": {"count": 0},
                           "scar": {"count": 0}})
    torch.testing.assert_close(_maps(SkinScene(cfg, 0), n=8).C_m, torch.full((1, 8, 8), 0.02))
    with pytest.raises(SceneError, match="base.*without a preset"):
        scene_from_dict({"base": {"preset": None, "C_m": 0.01}})


def _only(**features) -> SceneConfig:
    none = {"freckles": {"count": 0}, "scar": {"count": 0}, "veins": {"count": 0}, "hairs": {"count": 0}}
    flat = {"variation": {"C_m": 0, "beta_m": 0, "C_he": 0, "C_bc": 0, "C_hd": 0}}
    return scene_from_dict({**flat, **none, **features})


def test_freckles_are_melanin_spots_of_the_configured_strength():
    maps = _maps(SkinScene(_only(freckles={"count": 6, "radius_mm": [0.3, 0.3], "melanin_factor": [3.0, 3.0]}), 1), mm=0.02, n=425)
    base = TABLE2["III interior"]["C_m"]
    ratio = maps.C_m / base
    assert float(ratio.min()) == pytest.approx(1.0, abs=1e-6)
    assert 2.9 < float(ratio.max()) < 3.2  # a centre, or two overlapping rims
    for n in ("C_he", "C_hd", "beta_m"):
        torch.testing.assert_close(getattr(maps, n), torch.full_like(maps.C_m, TABLE2["III interior"][n]))


def test_scar_has_less_melanin_and_epidermal_blood_more_dermal_blood():
    maps = _maps(SkinScene(_only(scar={"count": 1, "width_mm": [0.8, 0.8]}), 2), mm=0.02, n=425)
    base = TABLE2["III interior"]
    inside = maps.C_m < 0.5 * base["C_m"]
    assert int(inside.sum()) > 1000  # mm² of scar on the grid
    torch.testing.assert_close(maps.C_m[inside].min(), torch.tensor(0.4 * base["C_m"]), rtol=1e-3, atol=0)
    torch.testing.assert_close(maps.C_he[inside].min(), torch.tensor(0.5 * base["C_he"]), rtol=1e-3, atol=0)
    torch.testing.assert_close(maps.C_hd[inside].max(), torch.tensor(1.5 * base["C_hd"]), rtol=1e-3, atol=0)


def test_a_vein_absorbs_as_deoxygenated_blood_a_hair_the_same_at_every_wavelength():
    vein = _maps(SkinScene(_only(veins={"count": 1, "blood_path_mm": 0.01}), 4), mm=0.02, n=425)
    blood = chromophore_spectra(WL).deoxy_blood
    peak = vein.absorbance[0].amax(dim=(1, 2)).double()
    torch.testing.assert_close(peak, blood * 0.01, rtol=1e-3, atol=0)  # the centre line lies on the grid
    on = vein.absorbance[0, 1] > 0
    torch.testing.assert_close(vein.absorbance[0, 0][on] / vein.absorbance[0, 1][on],
                               (blood[0] / blood[1]).float().expand(int(on.sum())), rtol=1e-4, atol=0)
    hair = _maps(SkinScene(_only(hairs={"count": 3, "absorbance": 2.5}), 4), mm=0.01, n=850)
    assert torch.equal(hair.absorbance[0, 0], hair.absorbance[0, 2])
    assert 2.4 < float(hair.absorbance.max()) <= 2.5 * 3  # up to three hairs crossing
    thin = (hair.absorbance[0, 0] > 0).float().mean()
    assert 0.002 < float(thin) < 0.05  # thin curves, not areas


def test_each_feature_draws_from_its_own_stream():
    few, many = (SkinScene(scene_from_dict({"freckles": {"count": c}}), 5) for c in (0, 40))
    a, b = _maps(few), _maps(many)
    assert torch.equal(a.absorbance, b.absorbance)  # veins and hairs unmoved
    assert not torch.equal(a.C_m, b.C_m)


def test_smooth_variation_has_the_configured_amplitude():
    cfg = _only(variation={"C_m": 0.25, "beta_m": 0, "C_he": 0, "C_bc": 0, "C_hd": 0, "length_scale_mm": 0.5})
    maps = SkinScene(cfg, 9).maps(0.05, 400, WL)
    log = torch.log(maps.C_m / TABLE2["III interior"]["C_m"])
    assert 0.15 < float(log.std()) < 0.35
    assert abs(float(log.mean())) < 0.1


@pytest.mark.parametrize(
    "data, match",
    [
        ({"freckles": {"radius_mm": [0.5, 0.1]}}, "freckles.radius_mm"),
        ({"base": {"preset": "VI palm"}}, "not a Table 2 row"),
        ({"hairs": {"count": -1}}, "hairs.count"),
        ({"veins": {"colour": "blue"}}, "veins.colour: unknown key"),
    ],
)
def test_bad_scene_values_name_the_key(data, match):
    with pytest.raises(SceneError, match=match):
        scene_from_dict(data, "my.yaml")


def test_bad_grid_is_refused():
    with pytest.raises(ValueError, match="mm_per_pixel > 0"):
        SkinScene().maps(0.0, 10, WL)
    assert math.isfinite(float(SkinScene().maps(0.1, 1, WL).C_m))
