"""Calibration settings: the shipped YAML is the embedded default; files and overrides are validated."""

from __future__ import annotations

import pytest

from skinlayers.calibration.corrections import band_factors, exposure_value, gray_card_level, reflectance_ratio, roi_to_superpixels
from skinlayers.calibration.errors import CalibrationError
from skinlayers.calibration.settings import CalibrationSettings, SettingsFileError, load_calibration_settings
from skinlayers.configs import config_path


def test_shipped_yaml_equals_the_defaults():
    assert load_calibration_settings(config_path("calibration.yaml")) == CalibrationSettings()
    assert load_calibration_settings() == CalibrationSettings()


def test_file_and_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("gray_card: false\ninterpolation: lanczos\n")
    s = load_calibration_settings(path, polarization=False)
    assert (s.gray_card, s.polarization, s.interpolation, s.flat_field) == (False, False, "lanczos", True)


@pytest.mark.parametrize(
    "text, match",
    [
        ("interpolation: nearest", "interpolation"),
        ("saturation_margin: -1", "saturation_margin"),
        ("gray_card_roi_px: [10, 10, 5, 20]", "gray_card_roi_px"),
    ],
)
def test_bad_files_name_the_key(tmp_path, text, match):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(SettingsFileError, match=match):
        load_calibration_settings(path)


def test_gray_card_box_in_superpixels():
    # raw [10, 21, 31, 40] → whole cells 5…15 × 11…20; a 15% inset trims ~3 raw px per side
    assert roi_to_superpixels([10, 21, 31, 40], (100, 100)) == (5, 11, 15, 20)
    assert roi_to_superpixels([10, 20, 30, 40], (100, 100), inset=0.15) == (7, 12, 13, 18)  # raw 13…27 × 23…37
    with pytest.raises(CalibrationError, match="no whole 2×2 cell"):
        roi_to_superpixels([10, 20, 11, 40], (100, 100))


def test_gray_card_level_refuses_a_clipped_or_dark_card():
    import numpy as np

    image = np.full((20, 20), 500.0, np.float32)
    saturated = np.zeros((20, 20), bool)
    assert gray_card_level(image, (2, 2, 8, 8), saturated, "f.dng") == 500.0
    saturated[3, 3] = True
    with pytest.raises(CalibrationError, match="f.dng: .* of the gray card is saturated"):
        gray_card_level(image, (2, 2, 8, 8), saturated, "f.dng")
    with pytest.raises(CalibrationError, match="no signal"):
        gray_card_level(image * 0, (2, 2, 8, 8), saturated * False, "f.dng")


def test_band_factors_follow_the_switches():
    from skinlayers.formats.manifest import Exposure
    from skinlayers.acquire.hardware.rig import load_rig

    rig = load_rig(targets={"spectralon_reflectance": {430: 0.98, 670: 0.99}})
    slow, fast = Exposure(iso=400, shutter_s=0.01, aperture_f=10), Exposure(iso=800, shutter_s=0.01, aperture_f=10)
    on = band_factors(
        CalibrationSettings(), rig, 550.0, gray_reference=110.0, gray_skin=100.0, exposure_reference=slow, exposure_skin=fast
    )
    assert on.flash_factor == pytest.approx(1.1) and on.exposure_ratio == 1.0
    assert on.spectralon_reflectance == pytest.approx(0.985)  # linear between the certified bands
    assert on.polarization_factor == pytest.approx(1.0527)
    off = band_factors(
        CalibrationSettings(gray_card=False, spectralon_reflectance=False, polarization=False),
        rig, 550.0, gray_reference=None, gray_skin=None, exposure_reference=slow, exposure_skin=fast,
    )
    assert (off.flash_factor, off.exposure_ratio, off.spectralon_reflectance, off.polarization_factor) == (1.0, 0.5, 1.0, 1.0)
    assert exposure_value(fast) == 2 * exposure_value(slow)


def test_reflectance_ratio_flat_field_or_scalar():
    import numpy as np

    skin = np.array([[10.0, 20.0], [30.0, 40.0]], np.float32)
    ref = np.array([[100.0, 0.0], [50.0, 200.0]], np.float32)
    out, ok = reflectance_ratio(skin, ref, 2.0)
    np.testing.assert_allclose(out, [[0.2, 0.0], [1.2, 0.4]])
    assert ok.tolist() == [[True, False], [True, True]]
    out, ok = reflectance_ratio(skin, ref, 1.0, flat=100.0)
    np.testing.assert_allclose(out, skin / 100.0)
