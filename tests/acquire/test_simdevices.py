"""The simulated wheel and camera: their base classes, timing, read-back, injected faults, and a
wheel at the wrong position showing in the picture."""

from __future__ import annotations

import numpy as np
import pytest
import rawpy

from skinlayers.acquire.hardware.devices import Camera, CameraError, ExposureSettings, FilterWheel, WheelError
from skinlayers.acquire.hardware.rig import load_rig
from skinlayers.acquire.hardware.simdevices import SimulatedCamera, SimulatedWheel
from skinlayers.acquire.simulator.simulated import SimulatedBench
from skinlayers.acquire.simulator.simulation_settings import simulation_from_dict

BANDS = [{"wavelength_nm": 550, "filter_position": 2, "iso": 200}, {"wavelength_nm": 650, "filter_position": 3, "iso": 400}]


def make_bench(seed: int = 21) -> SimulatedBench:
    rig = load_rig(bands=BANDS, geometry={"cube_px": 32, "rectify_px": 48})
    settings = simulation_from_dict({"motion": {"max_shift_px": 2.0}, "filters": {"wavelength_samples": 1}})
    bench = SimulatedBench(rig, None, settings, seed=seed, device="cpu")
    bench.set_target("spectralon")  # flat frames need no skin render
    return bench


def test_they_are_a_filter_wheel_and_a_camera():
    wheel = SimulatedWheel(time_scale=0.0)
    assert isinstance(wheel, FilterWheel)
    assert isinstance(SimulatedCamera(make_bench(), wheel), Camera)
    assert "12 positions" in wheel.identify()


def test_moves_take_the_shorter_way_round_scaled_by_time_scale():
    slept = []
    wheel = SimulatedWheel(12, seconds_per_step=0.5, settle_s=0.1, time_scale=0.5, sleep=slept.append)
    for target in (4, 12, 12, 2):
        wheel.move_to(target)
        assert wheel.position() == target
    assert slept == pytest.approx([0.5 * (0.1 + 0.5 * 3), 0.5 * (0.1 + 0.5 * 4), 0.5 * (0.1 + 0.5 * 2)])
    assert wheel.moves == 4
    instant = SimulatedWheel(6, time_scale=0.0, sleep=slept.append)
    instant.move_to(4)
    assert len(slept) == 3


def test_injected_wheel_faults_raise_and_leave_the_wheel_where_it_is():
    wheel = SimulatedWheel(12, time_scale=0.0, wrong_position={2: 5}, no_answer={3})
    wheel.move_to(3)
    with pytest.raises(WheelError, match="simulated wheel: asked for position 4, it reports 5"):
        wheel.move_to(4)
    assert wheel.position() == 5
    with pytest.raises(WheelError, match="no answer"):
        wheel.move_to(7)
    assert wheel.position() == 5
    wheel.move_to(7)
    assert wheel.position() == 7
    with pytest.raises(ValueError, match="simulated wheel: position 13 outside 1–12"):
        wheel.move_to(13)
    with pytest.raises(ValueError, match="6 or 12"):
        SimulatedWheel(8)


def test_a_wrong_wheel_position_shows_in_the_picture(tmp_path):
    """The wheel stops at 3 (650 nm) when asked for 2 (550 nm): the camera photographs what is there —
    the same picture a correct wheel at 3 gives, not the one at 2."""
    exposure = ExposureSettings(200, 0.01, 10.0)
    faulty = SimulatedWheel(12, time_scale=0.0, wrong_position={1: 3})
    camera = SimulatedCamera(make_bench(), faulty)
    camera.configure(exposure)
    with pytest.raises(WheelError):
        faulty.move_to(2)
    wrong = rawpy.imread(str(camera.capture(tmp_path / "wrong"))).raw_image.copy()
    pictures = {}
    for position in (2, 3):
        wheel = SimulatedWheel(12, time_scale=0.0)
        cam = SimulatedCamera(make_bench(), wheel)
        cam.configure(exposure)
        wheel.move_to(position)
        pictures[position] = rawpy.imread(str(cam.capture(tmp_path / f"at{position}"))).raw_image.copy()
    assert np.array_equal(wrong, pictures[3])
    assert np.abs(wrong.astype(float) - pictures[2]).mean() > 50  # another band: other channel levels


def test_the_opaque_slot_gives_a_black_frame(tmp_path):
    wheel = SimulatedWheel(12, time_scale=0.0)
    bench = make_bench()
    camera = SimulatedCamera(bench, wheel)
    camera.configure(ExposureSettings(400, 0.01, 10.0))
    for position in (bench.rig.wheel.dark_position, 7):  # 7: no filter in the rig, blanked
        wheel.move_to(position)
        with rawpy.imread(str(camera.capture(tmp_path / f"dark{position}"))) as r:
            assert abs(r.raw_image.astype(float).mean() - 1024) < 0.5
    assert [f.target for f in bench.frames] == ["dark", "dark"]


def test_configure_reads_back_and_refuses_what_the_camera_ignores():
    camera = SimulatedCamera(make_bench(), SimulatedWheel(time_scale=0.0))
    got = camera.configure(ExposureSettings(800, 0.01, 10.0))
    assert got == ExposureSettings(800, 0.01, 10.0)
    with pytest.raises(CameraError, match="simulated camera: iso asked ISO 700, the camera reports ISO 800"):
        camera.configure(ExposureSettings(700, 0.01, 10.0))
    with pytest.raises(CameraError, match="aperture asked f/10.5, the camera reports f/10"):
        camera.configure(ExposureSettings(800, 0.01, 10.5))
    assert camera.configure(ExposureSettings(640, 1 / 125, 11.0)) == ExposureSettings(640, 1 / 125, 11.0)


def test_capture_writes_a_dng_with_the_exposure_and_injected_failures_write_nothing(tmp_path):
    wheel = SimulatedWheel(12, time_scale=0.0)
    bench = make_bench()
    camera = SimulatedCamera(bench, wheel, fail_captures={2})
    camera.configure(ExposureSettings(400, 0.01, 10.0))
    wheel.move_to(3)
    path = camera.capture(tmp_path / "ref_650.raw")
    assert path == tmp_path / "ref_650.dng"
    with rawpy.imread(str(path)) as r:
        assert r.raw_image.shape == (bench.geometry.height_px, bench.geometry.width_px)
        assert r.white_level == 16383 and list(r.black_level_per_channel) == [1024] * 4
    with pytest.raises(CameraError, match="no frame delivered .*capture 2"):
        camera.capture(tmp_path / "lost")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ref_650.dng"]
    assert camera.capture(tmp_path / "again").exists()
    assert bench.frames[-1].iso == 400 and bench.frames[-1].band_nm == 650.0
    assert "simulated camera" in camera.identify()
