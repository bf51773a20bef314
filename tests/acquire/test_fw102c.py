"""The FW102C driver against a scripted serial transport fed byte-exact exchanges."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Optional

import pytest

from skinlayers.acquire.hardware.devices import FilterWheel, WheelError
from skinlayers.acquire.hardware.fw102c import FW102C

PORT = "/dev/ttyFAKE0"
IDN = b"THORLABS FW102C/FW212C Filter Wheel version 1.07"


@dataclass
class Repeat:
    """A scripted step that answers every consecutive write equal to ``expected`` (polling)."""

    expected: bytes
    reply: bytes


class ScriptedTransport:
    """Serial-like: each write must equal the next scripted request; its reply then becomes readable.

    A read with nothing pending waits the transport's timeout and returns b"" (as pyserial does).
    """

    def __init__(self, script: list, port: str = PORT) -> None:
        self.script = list(script)
        self.port = port
        self.timeout: Optional[float] = None
        self.pending = bytearray()
        self.written: list[bytes] = []
        self.discarded = bytearray()
        self.closed = False

    def write(self, data: bytes) -> int:
        self.written.append(bytes(data))
        while self.script and isinstance(self.script[0], Repeat) and self.script[0].expected != data:
            self.script.pop(0)
        assert self.script, f"unexpected write {data!r}: the script is done"
        step = self.script[0]
        if isinstance(step, Repeat):
            self.pending += step.reply
            return len(data)
        expected, reply = self.script.pop(0)
        assert data == expected, f"wrote {data!r}, the script expects {expected!r}"
        if reply:
            self.pending += reply
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if self.pending:
            out = bytes(self.pending[:size])
            del self.pending[:size]
            return out
        time.sleep(self.timeout or 0.0)
        return b""

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        self.discarded += self.pending
        self.pending.clear()

    def close(self) -> None:
        self.closed = True

    def assert_done(self) -> None:
        """Every scripted exchange happened and every byte the wheel sent was read, none discarded."""
        assert all(isinstance(step, Repeat) for step in self.script), f"exchanges left: {self.script}"
        assert not self.pending, f"left unread: {bytes(self.pending)!r}"
        assert not self.discarded, f"discarded unread: {bytes(self.discarded)!r}"


def reply(command: bytes, *lines: bytes, prompt: bytes = b"> ") -> bytes:
    return command + b"\r" + b"".join(line + b"\r" for line in lines) + prompt


PCOUNT6 = (b"pcount?\r", reply(b"pcount?", b"6"))


def wheel(script, **kw) -> tuple[FW102C, ScriptedTransport]:
    transport = ScriptedTransport(script)
    kw.setdefault("timeout_s", 0.1)
    kw.setdefault("move_timeout_s", 0.3)
    kw.setdefault("retries", 2)
    return FW102C(transport, **kw), transport


def test_is_a_filter_wheel():
    w, t = wheel([])
    assert isinstance(w, FilterWheel)
    assert t.written == []


def test_identify_position_count_and_position_byte_exact():
    w, t = wheel([
        (b"*idn?\r", reply(b"*idn?", IDN)),
        PCOUNT6,
        (b"pos?\r", reply(b"pos?", b"3")),
    ])
    assert w.identify() == IDN.decode()
    assert w.position_count == 6
    assert w.position() == 3
    assert w.position_count == 6  # asked once only
    assert t.written == [b"*idn?\r", b"pcount?\r", b"pos?\r"]
    assert w.port_name == PORT
    t.assert_done()


def test_move_reads_the_position_back():
    w, t = wheel([PCOUNT6, (b"pos=4\r", reply(b"pos=4")), (b"pos?\r", reply(b"pos?", b"4"))])
    w.move_to(4)
    assert t.written == [b"pcount?\r", b"pos=4\r", b"pos?\r"]
    t.assert_done()


def test_move_polls_until_the_wheel_reports_the_target():
    """A firmware that shows the prompt before the move ends: pos? reports the old position first."""
    w, t = wheel([
        PCOUNT6,
        (b"pos=5\r", reply(b"pos=5")),
        (b"pos?\r", reply(b"pos?", b"1")),
        (b"pos?\r", reply(b"pos?", b"6")),
        (b"pos?\r", reply(b"pos?", b"5")),
    ])
    w.move_to(5)
    assert t.written.count(b"pos?\r") == 3
    t.assert_done()


def test_prompt_without_space_and_stale_bytes_before_the_echo():
    """A late prompt of an earlier exchange is skipped; a bare '>' prompt ends the reply."""
    w, t = wheel([PCOUNT6, (b"pos?\r", b"> " + reply(b"pos?", b"2", prompt=b">"))])
    assert w.position() == 2
    t.assert_done()


def test_refused_command_raises_at_once_naming_port_and_exchange():
    answer = b"speed=1\rCommand error CMD_NOT_DEFINED\r\n> "
    w, t = wheel([(b"speed=1\r", answer)])
    with pytest.raises(WheelError) as err:
        w.set_fast(True)
    msg = str(err.value)
    assert PORT in msg and "CMD_NOT_DEFINED" in msg
    assert repr(b"speed=1\r") in msg and repr(answer) in msg
    assert t.written == [b"speed=1\r"]  # not retried: the wheel heard the command and refused it
    t.assert_done()


def test_no_answer_retried_then_error_naming_port_and_exchange():
    w, t = wheel([(b"*idn?\r", None)] * 3, timeout_s=0.1, retries=2)
    start = time.monotonic()
    with pytest.raises(WheelError) as err:
        w.identify()
    elapsed = time.monotonic() - start
    msg = str(err.value)
    assert PORT in msg and "no answer" in msg and "3 attempt(s)" in msg
    assert "sent b'*idn?\\r', received b''" in msg
    assert t.written == [b"*idn?\r"] * 3
    assert 0.3 <= elapsed < 1.0
    t.assert_done()


def test_timeout_then_success_on_retry():
    w, t = wheel([(b"*idn?\r", None), (b"*idn?\r", reply(b"*idn?", IDN))], retries=1)
    assert w.identify() == IDN.decode()
    assert t.written == [b"*idn?\r", b"*idn?\r"]
    t.assert_done()


def test_garbled_echo_retried():
    garbled = bytes(b ^ 0x20 if 0x21 <= b <= 0x7E and b != ord(">") else b for b in reply(b"pcount?", b"6"))
    w, t = wheel([(b"pcount?\r", garbled), PCOUNT6], retries=1)
    assert w.position_count == 6
    assert t.written == [b"pcount?\r", b"pcount?\r"]
    t.assert_done()


def test_unparseable_value_exhausts_retries():
    w, t = wheel([PCOUNT6] + [(b"pos?\r", reply(b"pos?", b"x3"))] * 2, retries=1)
    with pytest.raises(WheelError) as err:
        w.position()
    msg = str(err.value)
    assert "expected a number" in msg and "x3" in msg and PORT in msg
    assert "2 attempt(s)" in msg
    t.assert_done()


def test_position_outside_the_wheel_is_treated_as_garbled():
    w, t = wheel([PCOUNT6, (b"pos?\r", reply(b"pos?", b"9")), (b"pos?\r", reply(b"pos?", b"2"))], retries=1)
    assert w.position() == 2
    t.assert_done()


def test_wrong_position_after_move_repeats_the_move_then_raises():
    w, t = wheel(
        [
            PCOUNT6,
            (b"pos=4\r", reply(b"pos=4")),
            Repeat(b"pos?\r", reply(b"pos?", b"5")),
            (b"pos=4\r", reply(b"pos=4")),
            Repeat(b"pos?\r", reply(b"pos?", b"5")),
        ],
        move_timeout_s=0.2,
        retries=1,
    )
    with pytest.raises(WheelError) as err:
        w.move_to(4)
    msg = str(err.value)
    assert "asked for position 4, it reports 5" in msg and PORT in msg
    assert "received b'pos?\\r5\\r> '" in msg
    assert t.written.count(b"pos=4\r") == 2
    t.assert_done()


def test_wrong_position_recovered_by_the_repeated_move():
    w, t = wheel(
        [
            PCOUNT6,
            (b"pos=2\r", reply(b"pos=2")),
            Repeat(b"pos?\r", reply(b"pos?", b"3")),
            (b"pos=2\r", reply(b"pos=2")),
            (b"pos?\r", reply(b"pos?", b"2")),
        ],
        move_timeout_s=0.15,
        retries=1,
    )
    w.move_to(2)
    t.assert_done()


def test_missing_prompt_after_move_times_out_on_move_timeout():
    w, t = wheel([PCOUNT6, (b"pos=3\r", b"pos=3\r")], timeout_s=0.05, move_timeout_s=0.25, retries=0)
    start = time.monotonic()
    with pytest.raises(WheelError) as err:
        w.move_to(3)
    assert time.monotonic() - start >= 0.25
    assert "no prompt after 'pos=3'" in str(err.value)
    t.assert_done()


@pytest.mark.parametrize("bad", [0, 7, -1, 2.0, True, "3"])
def test_position_out_of_range_refused_before_sending(bad):
    w, t = wheel([PCOUNT6])
    with pytest.raises(ValueError, match=PORT):
        w.move_to(bad)
    assert t.written == [b"pcount?\r"]


def test_speed_and_sensors_set_and_read_back():
    w, t = wheel([
        (b"speed=0\r", reply(b"speed=0")),
        (b"speed?\r", reply(b"speed?", b"0")),
        (b"sensors=1\r", reply(b"sensors=1")),
        (b"sensors?\r", reply(b"sensors?", b"1")),
        (b"speed?\r", reply(b"speed?", b"0")),
    ])
    w.set_fast(False)
    w.set_sensors(True)
    assert w.is_fast() is False
    t.assert_done()


def test_setting_not_taken_raises():
    w, t = wheel([(b"sensors=0\r", reply(b"sensors=0")), (b"sensors?\r", reply(b"sensors?", b"1"))])
    with pytest.raises(WheelError, match="set sensors=0, it reports sensors=1"):
        w.set_sensors(False)
    t.assert_done()


def test_unexpected_pcount_raises():
    w, t = wheel([(b"pcount?\r", reply(b"pcount?", b"8"))])
    with pytest.raises(WheelError, match=f"{PORT}: it reports 8 positions, expected 6 or 12; last exchange"):
        _ = w.position_count
    t.assert_done()


def test_close_is_idempotent_and_blocks_further_use():
    w, t = wheel([])
    with w:
        pass
    assert t.closed
    w.close()
    with pytest.raises(WheelError, match="closed"):
        w.identify()


@pytest.mark.parametrize("kw", [{"timeout_s": 0}, {"move_timeout_s": -1}, {"retries": -1}])
def test_bad_settings_refused(kw):
    with pytest.raises(ValueError):
        FW102C(ScriptedTransport([]), **kw)


def test_every_exchange_is_logged_for_skinlayers_vv(caplog):
    """``skinlayers -vv``: each command sent and its answer, at DEBUG, naming the port."""
    w, _ = wheel([(b"*idn?\r", reply(b"*idn?", IDN)), PCOUNT6])
    with caplog.at_level(logging.DEBUG, logger="skinlayers.acquire.hardware.fw102c"):
        w.identify()
        assert w.position_count == 6
    said = [r.getMessage() for r in caplog.records if r.name == "skinlayers.acquire.hardware.fw102c"]
    assert len(said) == 2 and PORT in said[0] and "'*idn?'" in said[0] and IDN.decode() in said[0], said
    assert "'pcount?'" in said[1] and "'6'" in said[1], said
