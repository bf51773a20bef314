"""The device base classes: every driver and twin is a context manager that closes once, and the rules
a driver does not implement itself (position check, 6 or 12 positions, read-back) come from the base."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path
from typing import Callable, Optional

import pytest

from skinlayers.acquire.hardware.devices import Camera, CameraError, ExposureSettings, FilterWheel, WheelError
from skinlayers.acquire.hardware.fw102c import FW102C
from skinlayers.acquire.hardware.gphoto import GPhotoCamera
from skinlayers.acquire.hardware.rig import load_rig
from skinlayers.acquire.hardware.simdevices import SimulatedCamera, SimulatedWheel
from skinlayers.acquire.simulator.simulated import SimulatedBench
from skinlayers.acquire.simulator.simulation_settings import simulation_from_dict

# --- every device class as a context manager --------------------------------------------------------


class IdlePort:
    """A serial-like transport that is only opened and closed."""

    port = "/dev/ttyFAKE1"
    timeout: Optional[float] = None

    def close(self) -> None:
        pass


# What ``gphoto2 --auto-detect`` prints for one camera (gphoto2 2.5, actions.c: auto_detect_action).
FAKE_GPHOTO2 = """
import sys
if "--auto-detect" in sys.argv:
    print("%-30s %-16s" % ("Model", "Port"))
    print("-" * 58)
    print("%-30s %-16s" % ("Canon EOS 5D Mark II", "usb:001,004"))
"""


def _gphoto_camera(tmp_path: Path) -> GPhotoCamera:
    if sys.platform == "win32":
        pytest.skip("the fake gphoto2 is a POSIX script")
    program = tmp_path / "gphoto2"
    program.write_text(f"#!{sys.executable} -S\n" + textwrap.dedent(FAKE_GPHOTO2))
    program.chmod(0o755)
    return GPhotoCamera(executable=str(program))


def _simulated_camera(_tmp_path: Path) -> SimulatedCamera:
    rig = load_rig(bands=[{"wavelength_nm": 550, "filter_position": 2, "iso": 200}],
                   geometry={"cube_px": 32, "rectify_px": 48})
    settings = simulation_from_dict({"motion": {"max_shift_px": 2.0}, "filters": {"wavelength_samples": 1}})
    bench = SimulatedBench(rig, None, settings, seed=3, device="cpu")
    return SimulatedCamera(bench, SimulatedWheel(time_scale=0.0))


MAKERS: dict[str, Callable[[Path], object]] = {
    "FW102C": lambda _tmp_path: FW102C(IdlePort()),
    "GPhotoCamera": _gphoto_camera,
    "SimulatedWheel": lambda _tmp_path: SimulatedWheel(time_scale=0.0),
    "SimulatedCamera": _simulated_camera,
}


@pytest.fixture(params=list(MAKERS))
def device(request, tmp_path, monkeypatch):
    """A device of each class whose ``_close`` counts its calls in ``device.releases``."""
    dev = MAKERS[request.param](tmp_path)
    release = dev._close
    dev.releases = 0

    def counting_release() -> None:
        dev.releases += 1
        release()

    monkeypatch.setattr(dev, "_close", counting_release)
    return dev


def test_every_device_derives_from_its_base(device):
    assert isinstance(device, (FilterWheel, Camera))


def test_with_closes_on_leaving_the_block(device):
    with device as entered:
        assert entered is device
        assert not device.closed and device.releases == 0
    assert device.closed and device.releases == 1


def test_with_closes_on_an_error_and_lets_it_through(device):
    with pytest.raises(KeyError, match="inside the block"):
        with device:
            raise KeyError("inside the block")
    assert device.closed and device.releases == 1


def test_closing_twice_releases_once(device):
    device.close()
    device.close()
    with device:
        pass
    assert device.closed and device.releases == 1


def test_fw102c_closes_its_port():
    closes = []
    port = IdlePort()
    port.close = lambda: closes.append(1)
    with FW102C(port):
        pass
    assert closes == [1]


# --- the wheel's rules, in a wheel that implements only the primitives ------------------------------


class BareWheel(FilterWheel):
    """The primitives only; ``lands={asked: found}`` makes a move end elsewhere."""

    name = "bare wheel"

    def __init__(self, count: int = 6, lands: Optional[dict[int, int]] = None) -> None:
        self.count = count
        self.at = 1
        self.lands = lands or {}
        self.moves: list[int] = []

    def identify(self) -> str:
        return "bare wheel"

    def position(self) -> int:
        return self.at

    def _position_count(self) -> int:
        return self.count

    def _move(self, position: int) -> int:
        self.moves.append(position)
        self.at = self.lands.get(position, position)
        return self.at


@pytest.mark.parametrize("count", [6, 12])
def test_the_base_moves_to_every_position_of_a_6_or_12_position_wheel(count):
    wheel = BareWheel(count)
    assert wheel.position_count == count
    for target in range(1, count + 1):
        wheel.move_to(target)
    assert wheel.moves == list(range(1, count + 1)) and wheel.position() == count


@pytest.mark.parametrize(("count", "bad"), [(6, 0), (6, 7), (12, 13), (12, -1), (6, 2.0), (6, True), (6, "3"),
                                            (6, None)])
def test_the_base_refuses_a_position_outside_the_wheel_before_moving(count, bad):
    wheel = BareWheel(count)
    with pytest.raises(ValueError) as err:
        wheel.move_to(bad)
    assert str(err.value) == f"bare wheel: position {bad!r} outside 1–{count}"
    assert wheel.moves == []


def test_the_base_reads_the_position_back_after_a_move():
    wheel = BareWheel(12, lands={4: 5})
    wheel.move_to(3)
    with pytest.raises(WheelError) as err:
        wheel.move_to(4)
    assert str(err.value) == "bare wheel: asked for position 4, it reports 5"
    assert wheel.moves == [3, 4]


@pytest.mark.parametrize("count", [0, 5, 8, 10, 24])
def test_the_base_refuses_a_wheel_without_6_or_12_positions(count):
    wheel = BareWheel(count)
    message = f"bare wheel: it reports {count} positions, expected 6 or 12"
    with pytest.raises(WheelError) as err:
        _ = wheel.position_count
    assert str(err.value) == message
    with pytest.raises(WheelError, match=message):
        wheel.move_to(1)
    assert wheel.moves == []


def test_the_position_counts_are_one_constant_the_twin_keeps_too():
    assert FilterWheel.POSITION_COUNTS == (6, 12)
    with pytest.raises(ValueError, match="6 or 12"):
        SimulatedWheel(8)


def test_a_wheel_must_implement_the_primitives():
    class NoMove(FilterWheel):
        def identify(self) -> str:
            return ""

        def position(self) -> int:
            return 1

        def _position_count(self) -> int:
            return 6

    with pytest.raises(TypeError, match="_move"):
        NoMove()


# --- the camera's read-back, in a camera that implements only the primitives ------------------------


class BareCamera(Camera):
    """The primitives only; ``reports={setting: value}`` makes the camera read back another value
    (None: no number, shown as ``'bulb'``)."""

    name = "bare camera"

    def __init__(self, **reports: Optional[float]) -> None:
        self.reports = reports
        self.set: list[tuple[str, float]] = []

    def identify(self) -> str:
        return "bare camera"

    def capture(self, destination: Path) -> Path:
        return Path(destination)

    def _set(self, setting: str, value: float) -> tuple[Optional[float], str]:
        self.set.append((setting, value))
        found = self.reports.get(setting, value)
        return found, "'bulb'" if found is None else f"{found:g}"


EXPOSURE = ExposureSettings(iso=200, shutter_s=0.01, aperture_f=10.0)


def test_the_base_sets_every_setting_in_order_and_returns_what_the_camera_reports():
    camera = BareCamera(shutter=0.3, aperture=5.6)
    got = camera.configure(ExposureSettings(iso=200, shutter_s=1 / 3, aperture_f=5.657))
    assert got == ExposureSettings(iso=200, shutter_s=0.3, aperture_f=5.6)  # nominal values: within 1/6 stop
    assert camera.set == [("iso", 200.0), ("shutter", 1 / 3), ("aperture", 5.657)]


@pytest.mark.parametrize(
    ("reports", "message"),
    [
        ({"iso": 250}, "bare camera: iso asked ISO 200, the camera reports 250"),
        ({"shutter": 1 / 60}, "bare camera: shutter asked 1/100 s, the camera reports 0.0166667"),
        ({"shutter": None}, "bare camera: shutter asked 1/100 s, the camera reports 'bulb'"),
        ({"aperture": 11.0}, "bare camera: aperture asked f/10, the camera reports 11"),
    ],
)
def test_the_base_refuses_a_read_back_that_differs(reports, message):
    camera = BareCamera(**reports)
    with pytest.raises(CameraError) as err:
        camera.configure(EXPOSURE)
    assert str(err.value) == message
    refused = next(iter(reports))
    assert camera.set[-1][0] == refused  # the settings after it are not touched


@pytest.mark.parametrize(
    ("setting", "field", "found", "taken"),
    [
        ("iso", "iso", 224, True),  # log2(224/200) = 0.163 stop
        ("iso", "iso", 226, False),  # 0.176 stop
        ("aperture", "aperture_f", 10.5, True),  # 2·log2(10.5/10) = 0.141 stop: an f-number counts twice
        ("aperture", "aperture_f", 10.6, False),  # 0.168 stop
    ],
)
def test_the_tolerance_is_a_sixth_of_a_stop_of_exposure(setting, field, found, taken):
    camera = BareCamera(**{setting: found})
    if taken:
        assert getattr(camera.configure(EXPOSURE), field) == found
    else:
        with pytest.raises(CameraError, match=f"{setting} asked"):
            camera.configure(EXPOSURE)


def test_a_camera_that_reports_exact_values_sets_a_tighter_tolerance():
    class ExactCamera(BareCamera):
        readback_tolerance_stops = 1 / 32

    assert BareCamera(aperture=10.5).configure(EXPOSURE).aperture_f == 10.5
    with pytest.raises(CameraError, match="aperture asked f/10, the camera reports 10.5"):
        ExactCamera(aperture=10.5).configure(EXPOSURE)
    assert SimulatedCamera.readback_tolerance_stops == 1 / 32
    assert GPhotoCamera.readback_tolerance_stops == Camera.readback_tolerance_stops == 1 / 6


def test_the_nearest_offered_value_by_the_same_rule():
    camera = BareCamera()
    assert camera._nearest("aperture", 5.657, [4.0, 5.6, 8.0]) == 1
    assert camera._nearest("iso", 700.0, [640.0, 800.0]) == 0  # 0.13 stop
    assert camera._nearest("iso", 300.0, [200.0, 400.0]) is None  # 0.58 stop from either
    assert camera._nearest("iso", 200.0, []) is None


def test_a_camera_must_implement_the_primitives():
    class NoSet(Camera):
        def identify(self) -> str:
            return ""

        def capture(self, destination: Path) -> Path:
            return destination

    with pytest.raises(TypeError, match="_set"):
        NoSet()
