"""The one settings loader: defaults, then a file, then overrides merged by one rule; errors that name
the file and the key and stay short; every part's errors share one base."""

from __future__ import annotations

from typing import Optional

import pytest
from pydantic import Field

from skinlayers.formats.errors import InputError, SettingsError, SkinlayersError
from skinlayers.formats.settings import PixelBox, Strict, load_settings, merge


class Inner(Strict):
    a: int = 1
    b: int = 2


class Outer(Strict):
    name: str = "x"
    inner: Inner = Inner()
    box: Optional[PixelBox] = Field(None)


def test_merge_is_by_key_at_any_depth():
    base = {"inner": {"a": 5, "b": 6}, "name": "y", "list": [1, 2]}
    assert merge(base, {"inner": {"b": 7}, "list": [3]}) == {"inner": {"a": 5, "b": 7}, "name": "y", "list": [3]}
    assert merge(base, {"inner": 3}) == {"inner": 3, "name": "y", "list": [1, 2]}
    assert base["inner"] == {"a": 5, "b": 6}  # the base is not changed


def test_defaults_then_file_then_overrides(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text("name: from-file\ninner: {a: 10, b: 20}\n")
    assert load_settings(Outer) == Outer()
    s = load_settings(Outer, f, overrides={"inner": {"b": 30}})
    assert (s.name, s.inner.a, s.inner.b) == ("from-file", 10, 30)
    default = tmp_path / "shipped.yaml"
    default.write_text("name: shipped\n")
    assert load_settings(Outer, None, default_path=default).name == "shipped"
    assert load_settings(Outer, f, default_path=default).name == "from-file"  # a file replaces the shipped one


def test_errors_name_the_file_and_the_key(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text("inner: {a: many}\n")
    with pytest.raises(SettingsError) as err:
        load_settings(Outer, f)
    assert str(err.value).startswith(f"{f}: inner.a: ") and err.value.key == "inner.a"
    f.write_text("box: [5, 0, 1, 9]\n")
    with pytest.raises(SettingsError, match=r"box: .*0 <= x0 < x1"):
        load_settings(Outer, f)


def test_a_huge_rejected_value_is_not_printed_whole(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text("name: [" + ", ".join(["1"] * 100_000) + "]\n")
    with pytest.raises(SettingsError) as err:
        load_settings(Outer, f)
    assert len(str(err.value)) < 400


def test_every_parts_errors_share_the_base():
    from skinlayers.acquire import DeviceError, RigError, SceneError, SessionError, SimulationError
    from skinlayers.calibration import CalibrationError, FrameMissingError, SettingsFileError
    from skinlayers.formats.cube import CubeError
    from skinlayers.formats.manifest import ManifestError
    from skinlayers.model import SettingsError as ModelSettingsError
    from skinlayers.model.patch.maps import MapsError
    from skinlayers.reconstruct import FitSettingsError
    from skinlayers.reconstruct.spectrum.spectra_io import SpectraFileError

    for error in (RigError, SceneError, SimulationError, SettingsFileError, ModelSettingsError, FitSettingsError):
        assert issubclass(error, SettingsError), error
    for error in (SessionError, CalibrationError, CubeError, ManifestError, MapsError, SpectraFileError):
        assert issubclass(error, InputError) and issubclass(error, ValueError), error
    assert issubclass(DeviceError, SkinlayersError) and issubclass(DeviceError, RuntimeError)
    assert issubclass(FrameMissingError, SkinlayersError) and issubclass(FrameMissingError, FileNotFoundError)
    assert str(SkinlayersError("no such band", file="rig.yaml", key="bands")) == "rig.yaml: bands: no such band"


def _loaders():
    from skinlayers.acquire.hardware.rig import RigError, load_rig
    from skinlayers.acquire.simulator.scene import SceneError, load_scene
    from skinlayers.acquire.simulator.simulation_settings import SimulationError, load_simulation_settings
    from skinlayers.calibration import SettingsFileError, load_calibration_settings
    from skinlayers.model import SettingsError as ModelSettingsError
    from skinlayers.model import load_model_settings
    from skinlayers.reconstruct import FitSettingsError, load_fit_settings

    return {
        "model": (load_model_settings, ModelSettingsError), "rig": (load_rig, RigError), "scene": (load_scene, SceneError),
        "simulation": (load_simulation_settings, SimulationError), "calibration": (load_calibration_settings, SettingsFileError),
        "fit": (load_fit_settings, FitSettingsError),
    }


@pytest.mark.parametrize("part", ["model", "rig", "scene", "simulation", "calibration", "fit"])
@pytest.mark.parametrize(
    "text, needle",
    [
        (None, "cannot read"),
        ("key: [unclosed\n", "not valid YAML"),
        ("- a\n- b\n", "expected a mapping"),
        ("no_such_key: 1\n", "no_such_key: unknown key"),
    ],
)
def test_every_settings_file_is_read_by_the_one_loader(tmp_path, part, text, needle):
    """Each part's settings file: unreadable, not YAML, not a mapping or an unknown key is refused by
    the part's own error class, in one line naming the file."""
    load, error = _loaders()[part]
    path = tmp_path / f"{part}.yaml"
    if text is not None:
        path.write_text(text)
    with pytest.raises(error) as err:
        load(path)
    message = str(err.value)
    assert needle in message and str(path) in message and "\n" not in message
