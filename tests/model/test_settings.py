"""Model settings: the shipped YAML equals the embedded defaults; bad files get one clear message."""

from __future__ import annotations

from pathlib import Path

import pytest

from skinlayers.model import ModelSettings, SettingsError, load_model_settings

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "model.yaml"


def test_shipped_yaml_equals_defaults():
    assert load_model_settings(CONFIG) == ModelSettings()
    assert load_model_settings(None) == ModelSettings()


def test_partial_override(tmp_path):
    f = tmp_path / "m.yaml"
    f.write_text("optics:\n  epidermis_thickness_mm: 0.3\ntables:\n  n_gaussians: 18\n")
    s = load_model_settings(f)
    assert s.optics.epidermis_thickness_mm == 0.3 and s.tables.n_gaussians == 18
    assert s.optics.n_dermis == ModelSettings().optics.n_dermis


@pytest.mark.parametrize(
    "text, needle",
    [
        ("optics:\n  thicknes_mm: 0.3\n", "optics.thicknes_mm: unknown key"),
        ("optics:\n  epidermis_thickness_mm: -1\n", "optics.epidermis_thickness_mm"),
        ("optics:\n  epidermis_thickness_mm: thick\n", "optics.epidermis_thickness_mm"),
        ("render_wavelengths_nm: [300, 500]\n", "380–800"),
        ("tables:\n  sigma_a_min_per_mm: 5\n  sigma_a_max_per_mm: 1\n", "sigma_a_max_per_mm must exceed"),
    ],
)
def test_bad_files(tmp_path, text, needle):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(SettingsError) as err:
        load_model_settings(f)
    assert needle in str(err.value)
    assert str(f) in str(err.value)
    assert "\n" not in str(err.value)


def test_digest_changes_with_any_setting():
    a = ModelSettings()
    b = ModelSettings.model_validate({"optics": {"n_epidermis": 1.41}})
    assert a.digest() == ModelSettings().digest() != b.digest()
