"""Benchmark of the simulated bench at its default settings (on demand:
``pytest -m bench tests/bench/test_bench_simulated.py -s``).

Times what a default simulated session spends: the scene's maps on the truth grid, each band's true
skin render (3 wavelengths across the band, 582² truth grid plus the 3 mm border, every Gaussian), and
one frame of each kind (dark, Spectralon reference, skin) on the 1648×1184 sensor, DNG included.
``SKINLAYERS_BENCH_BANDS`` (default 2) sets how many of the nine bands are rendered; the first
carries the process's one-time start-up.
"""

from __future__ import annotations

import json
import os
import time

import pytest

from skinlayers.acquire.hardware.devices import ExposureSettings
from skinlayers.acquire.hardware.simdevices import SimulatedCamera, SimulatedWheel
from skinlayers.acquire.simulator.simulated import SimulatedBench

pytestmark = pytest.mark.bench


def test_default_session_timings(tmp_path):
    bench = SimulatedBench(seed=0)
    bands = bench.rig.bands[: int(os.environ.get("SKINLAYERS_BENCH_BANDS", "2"))]
    result = {"device": str(bench.device), "sensor_px": [bench.geometry.width_px, bench.geometry.height_px],
              "truth_grid_px": bench.truth_size_px, "white_electrons": round(bench.white_electrons, 1)}
    start = time.perf_counter()
    bench.scene_maps()
    result["scene_maps_s"] = round(time.perf_counter() - start, 2)
    result["band_render_s"] = {}
    for band in bands:
        result["band_render_s"][band.wavelength_nm] = round(bench.render_band(band.wavelength_nm).seconds, 2)
    wheel = SimulatedWheel(bench.rig.wheel.position_count, time_scale=0.0)
    camera = SimulatedCamera(bench, wheel)
    band = bands[0]
    camera.configure(ExposureSettings(band.iso, band.shutter_s, band.aperture_f))
    result["frame_s"] = {}
    for name, position, target in (("dark", bench.rig.wheel.dark_position, "skin"),
                                   ("reference", band.filter_position, "spectralon"), ("skin", band.filter_position, "skin")):
        wheel.move_to(position)
        bench.set_target(target)
        start = time.perf_counter()
        path = camera.capture(tmp_path / name)
        result["frame_s"][name] = round(time.perf_counter() - start, 2)
        assert path.stat().st_size > bench.geometry.width_px * bench.geometry.height_px
    print(json.dumps(result, indent=1))
