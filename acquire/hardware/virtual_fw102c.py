"""A virtual Thorlabs FW102C serving the wheel's ASCII protocol on a pseudo-terminal.

``VirtualFW102C`` opens a pty pair (``os.openpty``), puts it in raw mode (no echo, no CR/LF
translation by the tty: the device echoes as the real wheel does) and answers on the master side in a
daemon thread; ``.port`` is the slave's path, which pyserial (or a terminal program) opens like a
USB-serial port. The real driver ``FW102C`` thus runs unchanged over a real serial device path.

Behaviour, as ``fw102c`` documents the real wheel: a command ends with CR (LF is ignored); the reply is
the echo ``cmd\\r``, for a query the answer line ``value\\r``, for a bad keyword or argument
``Command error CMD_NOT_DEFINED`` / ``Command error CMD_ARG_INVALID`` (line end CR LF), then the prompt
``> ``. The wheel turns the short way round; a half turn takes ``half_turn_s`` at high speed (the
manual's 2.5 s by default; Bev.Instruments measured 2.9 s) and 6.8 / 2.9 times longer at low speed
(their measurement). The firmware is busy during a move: the echo of ``pos=n`` comes at once, the prompt
when the move ends, and commands sent meanwhile wait.

Faults, injected with ``inject(kind, times=None)`` — for every exchange from now on (``times=None``) or
for the next ``times`` exchanges they apply to:

* ``"silent"``: the command is swallowed, nothing comes back (any command);
* ``"garbled"``: the command is carried out but every printable byte of the reply except the prompt has
  bit 5 flipped, as line noise would (any command);
* ``"slow_move"``: the move takes ``slow_move_s`` instead (``pos=n`` only);
* ``"wrong_position"``: the wheel stops one position past the target (``pos=n`` only).

At the bench: ``python -m skinlayers.acquire.hardware.virtual_fw102c [--positions 6] [--fault silent:2]``
prints its port and serves until Ctrl-C. POSIX only (pseudo-terminals).
"""

from __future__ import annotations

import argparse
import os
import select
import threading
import time
import tty
from typing import Optional

__all__ = ["VirtualFW102C", "WHEEL_FAULTS", "main"]

WHEEL_FAULTS = ("silent", "garbled", "slow_move", "wrong_position")
_MOVE_FAULTS = ("slow_move", "wrong_position")
_SLOW_SPEED_FACTOR = 6.8 / 2.9
_NOT_DEFINED = b"Command error CMD_NOT_DEFINED\r\n"
_ARG_INVALID = b"Command error CMD_ARG_INVALID\r\n"
_PROMPT = b"> "


class VirtualFW102C:
    """A simulated FW102C on a pty; use as a context manager or with ``start()`` / ``stop()``."""

    def __init__(
        self,
        position_count: int = 12,
        *,
        half_turn_s: float = 2.5,
        slow_move_s: float = 30.0,
        start_position: int = 1,
        idn: str = "THORLABS FW102C/FW212C Filter Wheel version 1.07",
    ) -> None:
        if position_count not in (6, 12):
            raise ValueError(f"an FW102C has 6 or 12 positions, got {position_count}")
        if not 1 <= start_position <= position_count:
            raise ValueError(f"start_position {start_position} is not in 1…{position_count}")
        if half_turn_s < 0 or slow_move_s < 0:
            raise ValueError(f"move times must be >= 0, got half_turn_s={half_turn_s}, slow_move_s={slow_move_s}")
        self.position_count = position_count
        self.half_turn_s = float(half_turn_s)
        self.slow_move_s = float(slow_move_s)
        self.idn = idn
        self.position = start_position
        self.fast = True
        self.sensors = 0
        self.trigger = 0
        self.received: list[str] = []
        self._faults: dict[str, Optional[int]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._fds: list[int] = []
        self._port: Optional[str] = None

    # --- lifecycle ------------------------------------------------------------------------------

    @property
    def port(self) -> str:
        """Path of the pty slave (e.g. ``/dev/pts/5``) to open with pyserial."""
        if self._port is None:
            raise RuntimeError("the virtual FW102C is not started")
        return self._port

    def start(self) -> "VirtualFW102C":
        if self._thread is not None:
            raise RuntimeError("the virtual FW102C is already started")
        master, slave = os.openpty()
        wake_r, wake_w = os.pipe()
        self._fds = [master, slave, wake_r, wake_w]
        # Raw mode on the slave: the tty must neither echo what the device writes back to the master
        # nor turn CR into LF; the device does its own echo, as the real wheel does.
        tty.setraw(slave)
        # A full output queue (nobody reading) must lose bytes, as a serial line does, not block stop().
        os.set_blocking(master, False)
        self._master, self._wake_r, self._wake_w = master, wake_r, wake_w
        self._port = os.ttyname(slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name=f"VirtualFW102C {self._port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the pty (idempotent)."""
        if self._thread is None:
            return
        self._stop.set()
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5.0)
        self._thread = None
        for fd in self._fds:
            os.close(fd)
        self._fds = []
        self._port = None

    def __enter__(self) -> "VirtualFW102C":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # --- faults ---------------------------------------------------------------------------------

    def inject(self, kind: str, times: Optional[int] = None) -> None:
        """Inject a fault for every exchange (``times=None``) or the next ``times`` it applies to."""
        if kind not in WHEEL_FAULTS:
            raise ValueError(f"unknown wheel fault {kind!r}; choose one of {', '.join(WHEEL_FAULTS)}")
        if times is not None and times < 1:
            raise ValueError(f"times must be None (always) or >= 1, got {times}")
        with self._lock:
            self._faults[kind] = times

    def clear_faults(self) -> None:
        with self._lock:
            self._faults.clear()

    def _take_fault(self, kind: str) -> bool:
        with self._lock:
            if kind not in self._faults:
                return False
            left = self._faults[kind]
            if left is not None:
                if left <= 1:
                    del self._faults[kind]
                else:
                    self._faults[kind] = left - 1
            return True

    # --- serving --------------------------------------------------------------------------------

    def _serve(self) -> None:
        line = bytearray()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master, self._wake_r], [], [])
            if self._wake_r in ready:
                return
            try:
                data = os.read(self._master, 1024)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                # EIO: no slave side open; cannot happen while we hold the slave, but never spin.
                time.sleep(0.01)
                continue
            for byte in data:
                if byte == 0x0D:
                    self._handle(line.decode("ascii", "replace"))
                    line.clear()
                elif byte != 0x0A:
                    line.append(byte)
                if self._stop.is_set():
                    return

    def _send(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except OSError:  # output queue full (nobody reading): the bytes are lost, as on a serial line
            pass

    def _handle(self, command: str) -> None:
        with self._lock:
            self.received.append(command)
        if self._take_fault("silent"):
            return
        garbled = self._take_fault("garbled")
        echo = command.encode("ascii", "replace") + b"\r"
        answer, target = self._execute(command)
        if target is None:
            self._send(_garble(echo + answer) if garbled else echo + answer)
            self._send(_PROMPT)
            return
        self._send(_garble(echo) if garbled else echo)
        duration, stop_at = self._move_plan(target)
        if self._stop.wait(duration):
            return
        self.position = stop_at
        self._send(_PROMPT)

    def _move_plan(self, target: int) -> tuple[float, int]:
        """How long the move to ``target`` takes and where the wheel stops (faults applied)."""
        steps = abs(target - self.position)
        steps = min(steps, self.position_count - steps)
        duration = self.half_turn_s * steps / (self.position_count / 2)
        if not self.fast:
            duration *= _SLOW_SPEED_FACTOR
        if self._take_fault("slow_move"):
            duration = self.slow_move_s
        stop_at = target
        if self._take_fault("wrong_position"):
            stop_at = target % self.position_count + 1
        return duration, stop_at

    def _execute(self, command: str) -> tuple[bytes, Optional[int]]:
        """The answer lines of ``command`` and, for a valid ``pos=n``, the target of the move."""
        queries = {
            "*idn?": self.idn,
            "pos?": self.position,
            "pcount?": self.position_count,
            "speed?": int(self.fast),
            "sensors?": self.sensors,
            "trig?": self.trigger,
            "baud?": 1,
        }
        if command in queries:
            return f"{queries[command]}\r".encode("ascii"), None
        if command == "save":
            return b"", None
        name, sep, arg = command.partition("=")
        allowed = {
            "pos": range(1, self.position_count + 1),
            "pcount": (6, 12),
            "speed": (0, 1),
            "sensors": (0, 1),
            "trig": (0, 1),
        }
        if not sep or name not in allowed:
            return _NOT_DEFINED, None
        if not arg.isdigit() or int(arg) not in allowed[name]:
            return _ARG_INVALID, None
        value = int(arg)
        if name == "pos":
            return b"", value
        if name == "pcount":
            self.position_count = value
            self.position = min(self.position, value)
        elif name == "speed":
            self.fast = bool(value)
        elif name == "sensors":
            self.sensors = value
        else:
            self.trigger = value
        return b"", None


def _garble(data: bytes) -> bytes:
    """Flip bit 5 of every printable byte, as noise on the line would; CR/LF stay."""
    return bytes(b ^ 0x20 if 0x21 <= b <= 0x7E else b for b in data)


def _fault_arg(text: str) -> tuple[str, Optional[int]]:
    kind, _, times = text.partition(":")
    if kind not in WHEEL_FAULTS or (times and not times.isdigit()):
        raise argparse.ArgumentTypeError(f"expected KIND or KIND:N with KIND in {', '.join(WHEEL_FAULTS)}, got {text!r}")
    return kind, int(times) if times else None


def main(argv: Optional[list[str]] = None) -> None:
    """Serve a virtual FW102C on a pty until Ctrl-C; print the port to give ``--wheel-port``."""
    parser = argparse.ArgumentParser(
        prog="python -m skinlayers.acquire.hardware.virtual_fw102c",
        description="Serve a virtual Thorlabs FW102C filter wheel on a pseudo-terminal until Ctrl-C.",
    )
    parser.add_argument(
        "--positions", type=int, choices=(6, 12), default=12, help="positions of the wheel (the default rig has 12)"
    )
    parser.add_argument("--half-turn-s", type=float, default=2.5, help="time of a half turn at high speed (s)")
    parser.add_argument("--slow-move-s", type=float, default=30.0, help="duration of a move under the slow_move fault (s)")
    parser.add_argument(
        "--fault", type=_fault_arg, action="append", default=[], metavar="KIND[:N]",
        help=f"inject a fault always or for the next N exchanges; KIND is one of {', '.join(WHEEL_FAULTS)}",
    )
    args = parser.parse_args(argv)
    wheel = VirtualFW102C(args.positions, half_turn_s=args.half_turn_s, slow_move_s=args.slow_move_s)
    for kind, times in args.fault:
        wheel.inject(kind, times)
    with wheel:
        print(f"virtual FW102C ({args.positions} positions) on {wheel.port}  (Ctrl-C to stop)", flush=True)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            print("stopped", flush=True)


if __name__ == "__main__":
    main()
