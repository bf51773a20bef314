"""Driver of the Thorlabs FW102C / FW212C motorised filter wheel over its ASCII serial protocol.

The driver talks through an injected serial-like transport (pyserial's ``Serial`` or anything with
``read(size)``, ``write(data)``, ``flush()``, ``reset_input_buffer()``, ``close()`` and a settable
``timeout``), so tests feed it byte-exact exchanges and the pty twin (``virtual_fw102c``) exercises the
real serial path. ``FW102C.open(port, config)`` opens pyserial from a rig's ``WheelConfig``.

The protocol as this driver relies on it:

* Commands are lower case ASCII ending with CR; 115200 baud, 8 data bits, no parity, 1 stop bit, no
  flow control by default; a wrong keyword or an argument out of range makes the wheel answer an error
  string. (Thorlabs FW102C/FW212C manual, rev. H 2014, §5.2 "Keywords", and the ISIS/IBEX developers'
  manual page "Thorlabs FW102C Filter Wheel", which reproduces the command table.)
* The wheel echoes the command with its CR, answers a query on the next line, and then shows the
  prompt ``> ``. A terminal transcript of an FW102C, firmware 1.07 (matusm/Bev.Instruments.Thorlabs.FW,
  ``doc/ThorLabsFW.txt``) shows ``> pos?`` / ``3``, and the error lines ``Command error
  CMD_NOT_DEFINED`` (for ``POS=2``) and ``Command error CMD_ARG_INVALID`` (for ``pos=0`` and ``pos=7``
  on a six-position wheel). The byte framing ``pos?\\r`` → ``pos?\\r3\\r> `` is the one J. Feder's
  FW102C driver parses (read until ``b"> "``, strip the echo and the trailing ``\\r> ``) and the one
  InstrumentKit's Thorlabs protocol tests script (``freq?`` → ``freq?\\r20\\r>``).

What is not documented, and how the driver stays safe regardless:

* Whether the prompt after ``pos=n`` comes when the move starts or when it ends (Bev.Instruments waits
  up to the measured 2.9 s half-turn time for it). The driver waits up to ``move_timeout_s`` for the
  prompt and then polls ``pos?`` until the wheel reports the target, within the same deadline.
* Whether the prompt carries its trailing space on every firmware: ``>`` alone is accepted too.
* The line ending of the error line (the transcript shows an empty line after it): CR and LF are both
  taken as line ends and empty lines are ignored.

The rules every wheel keeps (6 or 12 positions, the check of a requested position, the read-back after
a move, closing) are ``FilterWheel``'s; this module adds the wheel's protocol, its waiting and retrying.

Every exchange starts by discarding unread input; bytes that arrive before the echo of the command
(a late prompt of an earlier exchange that timed out) are skipped. A silent, late or garbled exchange is
retried up to ``retries`` times; an error string is not (the wheel heard the command and refused it),
nor is a failure of the port itself (an unplugged USB-serial adapter).
A move that ends at the wrong position is repeated up to ``retries`` times. Failures raise
``WheelError`` naming the port and the last exchange: what was sent and what came back.
"""

from __future__ import annotations

import logging
import re
import time
from typing import Callable, Optional, Protocol, TypeVar

from .devices import FilterWheel, WheelError
from .rig import WheelConfig

log = logging.getLogger(__name__)

__all__ = ["FW102C", "SerialLike"]

T = TypeVar("T")

try:
    from termios import error as _TermiosError
except ImportError:  # Windows: no termios
    _TermiosError = OSError
# pyserial raises SerialException (an OSError) when a port fails, but lets termios.error through from
# tcflush when the device behind an open port is gone (measured on a pty whose master closed).
_PORT_ERRORS = (OSError, _TermiosError)

_PROMPT = ord(">")
_LINE_ENDS = b"\r\n"
_ERROR_MARKERS = ("Command error", "CMD_NOT_DEFINED", "CMD_ARG_INVALID")


class SerialLike(Protocol):
    """The part of pyserial's ``Serial`` the driver uses."""

    timeout: Optional[float]

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> Optional[int]: ...

    def flush(self) -> None: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


class _ExchangeFailed(Exception):
    """One attempt of an exchange got no, a late or a garbled answer (worth another try)."""


def _echo_end(command: bytes, received: bytes) -> Optional[int]:
    """Index just past the echo of ``command`` (followed by CR or LF) in ``received``, or None."""
    echo = re.search(re.escape(command) + rb"[\r\n]", received)
    return None if echo is None else echo.end()


def _answer_lines(command: bytes, received: bytes) -> Optional[list[str]]:
    """The answer lines of a complete reply in ``received``, or None while it is incomplete.

    A reply is complete when the echo of ``command`` has come and a prompt ``>`` stands at the start
    of a line after it. Bytes before the echo are stale and ignored.
    """
    end = _echo_end(command, received)
    if end is None:
        return None
    body = received[end:]
    if not body.endswith(b">") or (len(body) > 1 and body[-2] not in _LINE_ENDS):
        return None
    lines = re.split(rb"[\r\n]", body[:-1])
    return [line.decode("ascii", "replace").strip() for line in lines if line.strip()]


class FW102C(FilterWheel):
    """A Thorlabs FW102C/FW212C filter wheel on a serial-like ``transport``.

    ``timeout_s`` bounds the wait for one answer, ``move_timeout_s`` the wait for a move to end (prompt
    and read-back); ``retries`` is the number of extra attempts of a failed exchange or a move that
    ended elsewhere. ``port_name`` names the port in errors (default: the transport's ``port``).
    """

    def __init__(
        self,
        transport: SerialLike,
        *,
        timeout_s: float = 2.0,
        move_timeout_s: float = 10.0,
        retries: int = 2,
        port_name: Optional[str] = None,
    ) -> None:
        if not timeout_s > 0 or not move_timeout_s > 0 or retries < 0:
            raise ValueError(
                f"FW102C needs timeout_s > 0, move_timeout_s > 0 and retries >= 0, got "
                f"{timeout_s}, {move_timeout_s}, {retries}"
            )
        self._transport = transport
        self.timeout_s = float(timeout_s)
        self.move_timeout_s = float(move_timeout_s)
        self.retries = int(retries)
        self.port_name = port_name or str(getattr(transport, "port", None) or "serial transport")
        self.name = f"filter wheel on {self.port_name}"
        # Reads return after this slice at the latest, so deadlines are checked this often; set once
        # because pyserial reconfigures the port on every change of its timeout.
        self._slice_s = min(0.05, self.timeout_s)
        self._poll_s = min(0.1, self.move_timeout_s / 10)
        transport.timeout = self._slice_s
        self.last_exchange: tuple[bytes, bytes] = (b"", b"")
        self._count: Optional[int] = None

    @classmethod
    def open(cls, port: str, config: Optional[WheelConfig] = None) -> "FW102C":
        """Open ``port`` (a device path, COM name or pyserial URL) with the settings of ``config``.

        The wheel must answer ``*idn?`` and report ``config.position_count`` positions; otherwise
        ``WheelError`` naming the port (and the port is closed again).
        """
        import serial  # noqa: PLC0415 (pyserial is needed only when a real port is opened)

        config = config or WheelConfig(port=port)
        try:
            transport = serial.serial_for_url(
                port,
                baudrate=config.baud,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                xonxoff=False,
                rtscts=False,
                timeout=0.05,
                exclusive=True,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise WheelError(f"filter wheel: cannot open serial port {port!r}: {exc}") from None
        wheel = cls(
            transport,
            timeout_s=config.timeout_s,
            move_timeout_s=config.move_timeout_s,
            retries=config.retries,
            port_name=port,
        )
        try:
            wheel.identify()
            if wheel.position_count != config.position_count:
                raise WheelError(
                    f"filter wheel on {port}: it reports {wheel.position_count} positions, the rig "
                    f"config says wheel.position_count = {config.position_count}"
                )
        except BaseException:
            wheel.close()
            raise
        return wheel

    # --- FilterWheel ---------------------------------------------------------------------------

    def identify(self) -> str:
        """The wheel's ``*idn?`` line, e.g. ``THORLABS FW102C/FW212C Filter Wheel version 1.07``."""
        return self._transact("*idn?", _single_line)

    def position(self) -> int:
        """The position the wheel reports (``pos?``), 1 … ``position_count``."""
        count = self.position_count

        def in_range(lines: list[str]) -> int:
            value = _single_int(lines)
            if not 1 <= value <= count:
                raise _ExchangeFailed(f"position {value} outside 1…{count}")
            return value

        return self._transact("pos?", in_range)

    def _position_count(self) -> int:
        """``pcount?``, asked once."""
        if self._count is None:
            self._count = self._transact("pcount?", _single_int)
        return self._count

    def _move(self, position: int) -> int:
        """``pos=n``, repeated up to ``retries`` times while the wheel ends elsewhere; the position
        reported last."""
        for _ in range(self.retries):
            if self._move_once(position) == position:
                return position
        return self._move_once(position)

    def _move_once(self, position: int) -> int:
        """``pos=n``, then ``pos?`` until the wheel reports ``position`` or ``move_timeout_s`` has passed
        (a firmware may show the prompt when the move starts); the position reported last."""
        deadline = time.monotonic() + self.move_timeout_s
        self._transact(f"pos={position}", _no_answer, prompt_timeout_s=self.move_timeout_s)
        while True:
            reported = self.position()
            if reported == position or time.monotonic() >= deadline:
                return reported
            time.sleep(self._poll_s)

    def _close(self) -> None:
        self._transport.close()

    # --- further settings of the FW102C ---------------------------------------------------------

    def set_fast(self, fast: bool) -> None:
        """High (``speed=1``) or low (``speed=0``) move profile, read back with ``speed?``."""
        self._set_flag("speed", fast)

    def is_fast(self) -> bool:
        return self._transact("speed?", _single_int) == 1

    def set_sensors(self, active: bool) -> None:
        """Keep the position sensors on when idle (``sensors=1``) or off to avoid stray light (``0``)."""
        self._set_flag("sensors", active)

    def _set_flag(self, name: str, on: bool) -> None:
        self._transact(f"{name}={int(bool(on))}", _no_answer)
        found = self._transact(f"{name}?", _single_int)
        if found != int(bool(on)):
            raise self._error(f"set {name}={int(bool(on))}, it reports {name}={found}")

    # --- exchanges ------------------------------------------------------------------------------

    def _transact(
        self, command: str, parse: Callable[[list[str]], T], *, prompt_timeout_s: Optional[float] = None
    ) -> T:
        """Send ``command``, parse its answer lines; retry a silent, late or garbled exchange."""
        if self.closed:
            raise self._error(f"cannot send {command!r}: the port is closed")
        problem = ""
        for _ in range(self.retries + 1):
            try:
                lines = self._exchange(command, prompt_timeout_s or self.timeout_s)
                log.debug("%s: %r answered %r", self.name, command, lines)
                return parse(lines)
            except _ExchangeFailed as exc:
                problem = str(exc)
                log.info("%s: %r: %s", self.name, command, problem)
            except _PORT_ERRORS as exc:
                raise self._error(f"the serial port failed during {command!r}: {exc}") from None
        raise self._error(f"{problem} (after {self.retries + 1} attempt(s), timeout {self.timeout_s:g} s)")

    def _exchange(self, command: str, prompt_timeout_s: float) -> list[str]:
        """One attempt: write the command, read until its echo and a prompt; the answer lines."""
        command_bytes = command.encode("ascii")
        sent = command_bytes + b"\r"
        self._transport.reset_input_buffer()
        self._transport.write(sent)
        self._transport.flush()
        received = bytearray()
        self.last_exchange = (sent, b"")
        start = time.monotonic()
        echo_deadline = start + self.timeout_s
        prompt_deadline = start + max(prompt_timeout_s, self.timeout_s)
        echo_seen = False
        while True:
            chunk = self._transport.read(1)
            if chunk:
                received += chunk
                if chunk[-1] == _PROMPT:
                    # The prompt's trailing space, if this firmware sends one, belongs to this reply.
                    received += self._transport.read(1)
                self.last_exchange = (sent, bytes(received))
                lines = _answer_lines(command_bytes, bytes(received).rstrip(b" "))
                if lines is not None:
                    if any(marker in line for line in lines for marker in _ERROR_MARKERS):
                        raise self._error(f"it refused {command!r}: {' '.join(lines)}")
                    return lines
                echo_seen = echo_seen or _echo_end(command_bytes, bytes(received)) is not None
            now = time.monotonic()
            if now >= (prompt_deadline if echo_seen else echo_deadline):
                if not received:
                    raise _ExchangeFailed(f"no answer to {command!r}")
                if echo_seen:
                    raise _ExchangeFailed(f"no prompt after {command!r} within {prompt_deadline - start:g} s")
                raise _ExchangeFailed(f"garbled answer to {command!r}")

    def _error(self, what: str) -> WheelError:
        sent, received = self.last_exchange
        return WheelError(f"{self.name}: {what}; last exchange: sent {sent!r}, received {received!r}")


def _no_answer(lines: list[str]) -> None:
    if lines:
        raise _ExchangeFailed(f"unexpected answer {' '.join(lines)!r} to a command")


def _single_line(lines: list[str]) -> str:
    if len(lines) != 1:
        raise _ExchangeFailed(f"expected one answer line, got {lines!r}")
    return lines[0]


def _single_int(lines: list[str]) -> int:
    line = _single_line(lines)
    if not line.isdigit():
        raise _ExchangeFailed(f"expected a number, got {line!r}")
    return int(line)
