"""Simulation settings and the bench's closed forms: the shipped YAML, clear errors, the Bayer curves
against the measured camera they approximate, the flash, the band quadrature, blur and vignetting."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from skinlayers.acquire.simulator._optics import (CHANNELS, band_spectrum, blackbody, channel_sensitivity, gaussian_blur, sensor_geometry,
                                        vignetting)
from skinlayers.acquire.simulator.simulation_settings import (SimulationError, SimulationSettings, load_simulation_settings,
                                                    simulation_from_dict)


def test_embedded_default_is_the_shipped_yaml():
    assert load_simulation_settings() == SimulationSettings()


@pytest.mark.parametrize(
    "data, match",
    [
        ({"sensor": {"bit_depth": 14}}, "sensor.bit_depth"),
        ({"sensor": {"bit_depth": 12, "white_level": 16383}}, "white_level 16383 exceeds 4095"),
        ({"sensor": {"black_level": [1024, 1024, 1024, 20000]}}, "black_level"),
        ({"scene": {"gray_card_mm": [1, 1, 0, 2]}}, "gray_card_mm"),
        ({"truth": {"oversample": 1}}, "truth.oversample"),
        ({"camera": {"lens": "50mm"}}, "camera.lens: unknown key"),
    ],
)
def test_bad_settings_name_the_key(data, match):
    with pytest.raises(SimulationError, match=match):
        simulation_from_dict(data, "sim.yaml")


def test_bad_settings_files_name_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sensor: {bit_depth: 12, white_level: 9999}\n")
    with pytest.raises(SimulationError, match="bad.yaml: sensor: .*white_level 9999 exceeds 4095"):
        load_simulation_settings(bad)


def test_bayer_curves_follow_the_measured_nikon_d5100_within_six_percent_of_peak():
    colour = pytest.importorskip("colour")
    measured = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]
    w = np.arange(400.0, 701.0, 5.0)
    values = measured[w]
    curves = SimulationSettings().sensor.sensitivity
    for j, name in enumerate(CHANNELS):
        fitted = channel_sensitivity(curves[name], w)
        assert np.abs(fitted - values[:, j]).max() < 0.06 * values[:, j].max(), name
    assert w[np.argmax(channel_sensitivity(curves["green"], w))] == pytest.approx(535, abs=5)


def test_flash_is_planck_at_its_temperature():
    w = np.array([430.0, 560.0, 670.0])
    expected = (w / 560.0) ** -5 * np.expm1(1.438776877e7 / (560.0 * 6000.0)) / np.expm1(1.438776877e7 / (w * 6000.0))
    np.testing.assert_allclose(blackbody(w, 6000.0), expected, rtol=1e-12)
    peak = 2.897771955e6 / 6000.0  # Wien's displacement law (nm)
    grid = np.linspace(400, 560, 1601)
    assert grid[np.argmax(blackbody(grid, 6000.0))] == pytest.approx(peak, abs=0.2)


def test_band_quadrature_integrates_the_gaussian_filter():
    curves = SimulationSettings().sensor.sensitivity
    band = band_spectrum(610.0, 10.0, 5, 6000.0, curves)
    dense = np.linspace(560.0, 660.0, 20001)
    sigma = 10.0 / (2 * math.sqrt(2 * math.log(2)))
    filt = np.exp(-0.5 * ((dense - 610.0) / sigma) ** 2)
    step = dense[1] - dense[0]
    for j, name in enumerate(CHANNELS):
        integral = (filt * blackbody(dense, 6000.0) * channel_sensitivity(curves[name], dense)).sum() * step
        assert band.channel_signal[j] == pytest.approx(integral, rel=2e-3), name
    w = band.truth_weights()
    assert w.sum() == pytest.approx(1.0) and np.all(w > 0)
    direct = band.weights[0] + 2 * band.weights[1] + band.weights[2]
    np.testing.assert_allclose(w, direct / direct.sum())


def test_blur_keeps_light_and_has_its_sigma():
    image = torch.zeros(1, 61, 61, dtype=torch.float64)
    image[0, 30, 30] = 1.0
    out = gaussian_blur(image, 1.5)[0]
    assert float(out.sum()) == pytest.approx(1.0, rel=1e-12)
    x = torch.arange(61, dtype=torch.float64) - 30
    assert float((out.sum(0) * x**2).sum()) == pytest.approx(1.5**2, rel=1e-3)


def test_vignetting_is_thirty_percent_at_the_corners():
    geo = sensor_geometry(7.5, 1024, 270.0, 30.0, (12.0, 10.0))
    v = vignetting(geo, 0.3, torch.float64)
    assert float(v.max()) == pytest.approx(1.0, abs=1e-6)
    for corner in (v[0, 0], v[0, -1], v[-1, 0], v[-1, -1]):
        assert float(corner) == pytest.approx(0.7)
    assert geo.width_px % 16 == 0 and geo.height_px % 16 == 0
    assert (geo.width_px, geo.height_px) == (1648, 1184)
