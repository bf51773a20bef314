"""Real instruments, opt-in: a wheel when SKINLAYERS_WHEEL_PORT names its port (and
SKINLAYERS_WHEEL_POSITIONS its position count, default 6), a camera when SKINLAYERS_CAMERA=1 (with
SKINLAYERS_CAMERA_MODEL / SKINLAYERS_CAMERA_PORT to choose one). Skipped otherwise.

The camera test fires the camera (and its flash) once and sets f/10, 1/100 s, ISO 200 (DWRR08 §6);
put the camera in manual (M) mode first.
"""

from __future__ import annotations

import os

import pytest

from skinlayers.acquire.hardware.devices import ExposureSettings
from skinlayers.acquire.hardware.rig import CameraConfig, WheelConfig

WHEEL_PORT = os.environ.get("SKINLAYERS_WHEEL_PORT")
CAMERA = os.environ.get("SKINLAYERS_CAMERA") == "1"


@pytest.mark.skipif(not WHEEL_PORT, reason="set SKINLAYERS_WHEEL_PORT to test a real FW102C")
def test_real_wheel_moves_and_reads_back():
    from skinlayers.acquire.hardware.fw102c import FW102C

    count = int(os.environ.get("SKINLAYERS_WHEEL_POSITIONS", "6"))
    with FW102C.open(WHEEL_PORT, WheelConfig(port=WHEEL_PORT, position_count=count)) as wheel:
        assert "FW" in wheel.identify()
        start = wheel.position()
        for target in (start % count + 1, (start + count // 2 - 1) % count + 1, start):
            wheel.move_to(target)
            assert wheel.position() == target


@pytest.mark.skipif(not CAMERA, reason="set SKINLAYERS_CAMERA=1 to test a real camera through gphoto2")
def test_real_camera_configures_and_captures(tmp_path):
    from skinlayers.acquire.hardware.gphoto import RAW_SUFFIXES, GPhotoCamera

    config = CameraConfig(model=os.environ.get("SKINLAYERS_CAMERA_MODEL"), port=os.environ.get("SKINLAYERS_CAMERA_PORT"))
    with GPhotoCamera(config) as camera:
        assert camera.model in camera.identify()
        got = camera.configure(ExposureSettings(iso=200, shutter_s=0.01, aperture_f=10.0))
        assert (got.iso, got.shutter_s, got.aperture_f) == (200, pytest.approx(0.01), pytest.approx(10.0))
        written = camera.capture(tmp_path / "frame")
        assert written.suffix.lower() in RAW_SUFFIXES and written.stat().st_size > 1_000_000
