"""Simulated instruments: an in-process filter wheel and a camera that photographs a ``SimulatedBench``.

They derive from ``FilterWheel`` and ``Camera`` and so keep the real drivers' rules (position check,
read-back, closing, use with ``with``); a session runs on them unchanged. The camera asks the wheel
object it was given for its position at every exposure — that wheel may be the ``SimulatedWheel`` or
a real FW102C driver talking to the serial twin — so a wheel at the wrong position shows in the
picture, as it would at the bench. Faults can be injected into both.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable, Mapping, Optional

from .devices import EXPOSURE_FIELDS, Camera, CameraError, ExposureSettings, FilterWheel, show_setting
from .dng import write_dng

if TYPE_CHECKING:
    from ..simulator.simulated import SimulatedBench

__all__ = ["SimulatedCamera", "SimulatedWheel"]


class SimulatedWheel(FilterWheel):
    """A motorised filter wheel in the process (positions 1 … ``position_count``).

    A move takes ``settle_s + seconds_per_step ×`` the positions crossed (the shorter way round),
    times ``time_scale`` (1: as assumed for a real wheel; 0: at once, for tests). The defaults are
    assumptions of this simulator, not a datasheet's figures; set them from your wheel.

    Faults, counted by move (the first ``move_to`` is move 1): ``wrong_position={n: p}`` — move n
    stops at p (the wheel reports p, and ``move_to``'s read-back raises ``WheelError``);
    ``no_answer={n}`` — move n does not happen and raises ``WheelError``.
    """

    name = "simulated wheel"
    POSITION_COUNTS_SAID = "6 or 12"

    def __init__(
        self, position_count: int = 12, *, position: int = 1, seconds_per_step: float = 0.4, settle_s: float = 0.1,
        time_scale: float = 1.0, wrong_position: Mapping[int, int] | None = None, no_answer: Iterable[int] = (),
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if position_count not in self.POSITION_COUNTS:
            raise ValueError(f"a {self.name} has {self.POSITION_COUNTS_SAID} positions, not {position_count}")
        if not 1 <= position <= position_count:
            raise ValueError(f"start position {position} outside 1–{position_count}")
        if time_scale < 0 or seconds_per_step < 0 or settle_s < 0:
            raise ValueError("wheel times and time_scale must be >= 0")
        self._count = position_count
        self._position = position
        self._step_s, self._settle_s, self._scale = seconds_per_step, settle_s, time_scale
        self._wrong = dict(wrong_position or {})
        self._silent = set(no_answer)
        self._sleep = sleep
        self.moves = 0

    def identify(self) -> str:
        return f"skinlayers simulated filter wheel ({self._count} positions)"

    def position(self) -> int:
        return self._position

    def _position_count(self) -> int:
        return self._count

    def _move(self, position: int) -> int:
        self.moves += 1
        if self.moves in self._silent:
            raise self._error(f"no answer to the move to position {position} (injected fault, move {self.moves})")
        target = self._wrong.get(self.moves, position)
        d = abs(target - self._position)
        steps = min(d, self._count - d)
        if self._scale > 0 and steps:
            self._sleep(self._scale * (self._settle_s + self._step_s * steps))
        self._position = target
        return target


class SimulatedTunableFilter(SimulatedWheel):
    """A tunable filter (liquid-crystal or acousto-optic) stepping through up to ``MAX_SETTINGS`` pass bands
    as a wheel steps through positions: the simulated rig of many bands (31 of 10 nm, 400–700 nm, as
    hyperspectral skin datasets are taken), setting 1 its closed state."""

    name = "simulated tunable filter"
    MAX_SETTINGS = 64
    POSITION_COUNTS = tuple(range(2, MAX_SETTINGS + 2))
    POSITION_COUNTS_SAID = f"2–{MAX_SETTINGS + 1}"

    def identify(self) -> str:
        return f"skinlayers simulated tunable filter ({self._count} settings)"


class SimulatedCamera(Camera):
    """A camera with flash photographing ``bench`` through ``wheel``; writes uncompressed DNG files.

    Settings outside the sensor's lists (``sensor.iso_values``, ``shutter_values_s``,
    ``aperture_values``) are ignored, as cameras ignore them, and the read-back raises
    ``CameraError``. ``fail_captures={n}``: capture n (1-based) delivers no frame (``CameraError``).
    A frame's file is written atomically and replaces a file of the same name.
    """

    name = "simulated camera"
    # It reports exactly the listed value it took, so it needs no room for nominal values: 1/32 stop
    # still takes a value within 1% of a listed one (1% of an f-number is 0.029 stop) and refuses one
    # between two of its third stops, so that a setting it ignores shows in the read-back.
    readback_tolerance_stops = 1 / 32

    def __init__(self, bench: "SimulatedBench", wheel: FilterWheel, *, fail_captures: Iterable[int] = ()) -> None:
        self.bench = bench
        self.wheel = wheel
        self._fail = set(fail_captures)
        self._exposure = ExposureSettings(100, 1 / 125, 8.0)
        self.captures = 0

    def identify(self) -> str:
        g, s = self.bench.geometry, self.bench.settings.sensor
        return f"skinlayers simulated camera ({g.width_px}×{g.height_px} px, {s.bit_depth}-bit RGGB, seed {self.bench.seed})"

    def capture(self, destination: Path) -> Path:
        self.captures += 1
        if self.captures in self._fail:
            raise CameraError(f"simulated camera: no frame delivered (injected fault, capture {self.captures})")
        position = self.wheel.position()
        raw = self.bench.frame(position, self._exposure)
        s, e = self.bench.settings.sensor, self._exposure
        return write_dng(
            Path(destination).with_suffix(".dng"), raw, bits=s.bit_depth, black_level=s.black_level, white_level=s.white_level,
            iso=e.iso, exposure_s=e.shutter_s, f_number=e.aperture_f, model="simulated camera",
        )

    def _set(self, setting: str, value: float) -> tuple[Optional[float], str]:
        """Take the listed value that counts as ``value``; keep the current one if there is none."""
        allowed = getattr(self.bench.settings.sensor, _ALLOWED[setting])
        field = EXPOSURE_FIELDS[setting]
        best = self._nearest(setting, value, allowed)
        if best is not None:
            self._exposure = replace(self._exposure, **{field: allowed[best]})
        found = getattr(self._exposure, field)
        return found, show_setting(setting, found)


_ALLOWED = {"iso": "iso_values", "shutter": "shutter_values_s", "aperture": "aperture_values"}
