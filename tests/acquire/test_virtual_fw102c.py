"""The real FW102C driver over a real serial device path: the virtual wheel on a pseudo-terminal."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX only")

serial = pytest.importorskip("serial")

from skinlayers.acquire.hardware.devices import WheelError  # noqa: E402
from skinlayers.acquire.hardware.fw102c import FW102C  # noqa: E402
from skinlayers.acquire.hardware.rig import WheelConfig  # noqa: E402
from skinlayers.acquire.hardware.virtual_fw102c import VirtualFW102C, main  # noqa: E402

# Fast timing: a half turn in 30 ms; the driver waits 0.25 s for an answer and 0.3 s for a move.
HALF_TURN_S = 0.03
TIMEOUT_S = 0.25
MOVE_TIMEOUT_S = 0.3


@pytest.fixture
def virtual():
    with VirtualFW102C(6, half_turn_s=HALF_TURN_S, slow_move_s=0.4) as vw:
        yield vw


@pytest.fixture
def driver(virtual):
    port = serial.Serial(virtual.port, 115200, timeout=0.05)
    w = FW102C(port, timeout_s=TIMEOUT_S, move_timeout_s=MOVE_TIMEOUT_S, retries=2, port_name=virtual.port)
    yield w
    w.close()


@pytest.fixture
def driver_one_retry(virtual):
    """Persistent faults: two attempts are enough to show the retry and keep the test short."""
    port = serial.Serial(virtual.port, 115200, timeout=0.05)
    w = FW102C(port, timeout_s=TIMEOUT_S, move_timeout_s=MOVE_TIMEOUT_S, retries=1, port_name=virtual.port)
    yield w
    w.close()


def raw_exchange(port: str, data: bytes) -> bytes:
    """What the virtual wheel sends back for ``data``, read until its prompt."""
    with serial.Serial(port, 115200, timeout=0.5) as s:
        s.write(data)
        return s.read_until(b"> ")


def test_wire_format_echo_answer_prompt(virtual):
    assert raw_exchange(virtual.port, b"pos?\r") == b"pos?\r1\r> "
    assert raw_exchange(virtual.port, b"pos=3\r") == b"pos=3\r> "
    assert raw_exchange(virtual.port, b"POS=2\r") == b"POS=2\rCommand error CMD_NOT_DEFINED\r\n> "
    assert raw_exchange(virtual.port, b"pos=7\r") == b"pos=7\rCommand error CMD_ARG_INVALID\r\n> "
    assert virtual.position == 3


def test_identify_count_and_moves_all_round(virtual, driver):
    assert driver.identify() == "THORLABS FW102C/FW212C Filter Wheel version 1.07"
    assert driver.position_count == 6
    assert driver.position() == 1
    for target in (2, 4, 6, 1, 5, 3, 3):
        driver.move_to(target)
        assert driver.position() == target
        assert virtual.position == target


def test_move_time_follows_the_short_way_round(virtual, driver):
    driver.move_to(6)  # 1 → 6 is one step backwards
    start = time.monotonic()
    driver.move_to(3)  # 6 → 3: a half turn
    assert time.monotonic() - start >= HALF_TURN_S


def test_twelve_positions():
    with VirtualFW102C(12, half_turn_s=HALF_TURN_S) as vw, serial.Serial(vw.port, timeout=0.05) as port:
        w = FW102C(port, timeout_s=TIMEOUT_S, move_timeout_s=MOVE_TIMEOUT_S)
        assert w.position_count == 12
        w.move_to(12)
        w.move_to(7)
        assert vw.position == 7 and w.position() == 7


def test_speed_and_sensors(virtual, driver):
    driver.set_fast(False)
    assert driver.is_fast() is False and virtual.fast is False
    driver.set_sensors(True)
    assert virtual.sensors == 1
    driver.move_to(2)
    assert virtual.position == 2


@pytest.mark.parametrize("kind", ["silent", "garbled"])
def test_one_bad_exchange_is_retried(virtual, driver, kind):
    virtual.inject(kind, times=1)
    assert driver.position_count == 6
    assert virtual.received.count("pcount?") == 2


def test_slow_move_once_succeeds_on_retry(virtual, driver):
    virtual.inject("slow_move", times=1)
    driver.move_to(4)
    assert virtual.position == 4
    assert virtual.received.count("pos=4") == 2


def test_wrong_position_once_is_corrected(virtual, driver):
    virtual.inject("wrong_position", times=1)
    driver.move_to(3)
    assert virtual.position == 3
    assert virtual.received.count("pos=3") == 2


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("silent", "no answer to 'pcount?'"),
        ("garbled", "garbled answer to 'pcount?'"),
    ],
)
def test_persistent_exchange_fault_gives_clear_error(virtual, driver_one_retry, kind, message):
    virtual.inject(kind)
    with pytest.raises(WheelError) as err:
        _ = driver_one_retry.position_count
    msg = str(err.value)
    assert message in msg and virtual.port in msg and "sent b'pcount?\\r'" in msg
    assert "2 attempt(s)" in msg
    assert virtual.received.count("pcount?") == 2


def test_persistent_slow_move_gives_clear_error(virtual, driver_one_retry):
    assert driver_one_retry.position_count == 6
    virtual.inject("slow_move")
    with pytest.raises(WheelError) as err:
        driver_one_retry.move_to(5)
    msg = str(err.value)
    assert virtual.port in msg and "'pos=5'" in msg and "sent b'pos=5\\r'" in msg


def test_persistent_wrong_position_never_reports_success(virtual, driver_one_retry):
    virtual.inject("wrong_position")
    with pytest.raises(WheelError) as err:
        driver_one_retry.move_to(2)
    assert "asked for position 2, it reports 3" in str(err.value)
    assert virtual.position == 3
    assert virtual.received.count("pos=2") == 2


def test_port_vanishing_under_the_driver_gives_clear_error(virtual, driver):
    """As when the USB-serial adapter is unplugged: the device side of the open port goes away."""
    port = virtual.port
    assert driver.position_count == 6
    virtual.stop()
    with pytest.raises(WheelError, match="the serial port failed during 'pos\\?'") as err:
        driver.position()
    assert port in str(err.value)


def test_open_from_rig_config_checks_position_count(virtual):
    config = WheelConfig(port=virtual.port, position_count=6, timeout_s=TIMEOUT_S, move_timeout_s=MOVE_TIMEOUT_S)
    with FW102C.open(virtual.port, config) as w:
        w.move_to(2)
        assert virtual.position == 2
    wrong = WheelConfig(port=virtual.port, position_count=12, timeout_s=TIMEOUT_S)
    with pytest.raises(WheelError, match=r"reports 6 positions.*position_count = 12"):
        FW102C.open(virtual.port, wrong)


def test_open_missing_port_names_it(tmp_path):
    missing = str(tmp_path / "ttyUSB9")
    with pytest.raises(WheelError, match="cannot open serial port") as err:
        FW102C.open(missing, WheelConfig(port=missing))
    assert missing in str(err.value)


def test_open_silent_port_names_it():
    virtual = VirtualFW102C(6)
    virtual.inject("silent")
    with virtual:
        with pytest.raises(WheelError, match="no answer to '\\*idn\\?'") as err:
            FW102C.open(virtual.port, WheelConfig(timeout_s=0.1, retries=0))
        assert virtual.port in str(err.value)


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to count descriptors")
def test_stops_cleanly_without_leaks():
    threads, fds = threading.active_count(), _open_fds()
    for _ in range(3):
        vw = VirtualFW102C(6, half_turn_s=5.0).start()
        with serial.Serial(vw.port, timeout=0.05) as port:
            port.write(b"pos=4\r")  # a long move is under way when the twin stops
            time.sleep(0.05)
        start = time.monotonic()
        vw.stop()
        assert time.monotonic() - start < 1.0
        vw.stop()
    assert threading.active_count() == threads
    assert _open_fds() == fds
    with pytest.raises(RuntimeError):
        _ = vw.port


def test_bad_arguments_refused():
    with pytest.raises(ValueError):
        VirtualFW102C(8)
    with pytest.raises(ValueError):
        VirtualFW102C(6, start_position=7)
    with pytest.raises(ValueError, match="unknown wheel fault"):
        VirtualFW102C(6).inject("smoke")
    with pytest.raises(ValueError):
        VirtualFW102C(6).inject("silent", times=0)


def test_module_entry_prints_port_and_serves(monkeypatch, capsys):
    """``python -m skinlayers.acquire.hardware.virtual_fw102c`` serves until Ctrl-C (interrupted here)."""
    served = {}

    def fake_sleep(_seconds):
        port = capsys.readouterr().out.split(" on ")[1].split()[0]
        served["answer"] = raw_exchange(port, b"pcount?\r")
        raise KeyboardInterrupt

    monkeypatch.setattr(time, "sleep", fake_sleep)
    main(["--positions", "12", "--fault", "garbled:1"])
    assert served["answer"] == b"PCOUNT\x1f\r\x11\x12\r> "
    assert "stopped" in capsys.readouterr().out
