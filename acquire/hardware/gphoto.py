"""A camera driven through the ``gphoto2`` command line (no python-gphoto2 needed).

``GPhotoCamera(config)`` finds the camera with ``gphoto2 --auto-detect`` (chosen by the rig's
``camera.model`` / ``camera.port`` when several are connected) and then names it with ``--camera`` and
``--port`` on every call. What the driver relies on, from the gphoto2 sources (gphoto2/actions.c and
main.c, libgphoto2 camlibs/ptp2/config.c) and man page:

* ``--auto-detect`` prints a ``Model``/``Port`` header, a line of dashes, then ``%-30s %-16s`` rows; a
  model name may contain spaces, a port (``usb:001,004``) does not. Some systems list a camera twice,
  once with the bare port ``usb:``; that row is dropped when a full one names the same model.
* ``--get-config NAME`` prints ``Label:``, ``Type:``, ``Current: value`` and, for menus, ``Choice: i
  value`` lines; these keywords are not translated, and the driver runs gphoto2 under ``LC_ALL=C``.
* ``--set-config-value NAME=VALUE`` sets a menu entry by its text. (``--set-config`` would take a value
  that parses as an integer but is not a choice as a choice *index*, so ``1/100`` could become entry 1.)
  A camera ignores a value it does not accept without an error: every setting is read back.
* Configuration names differ by vendor: ISO is ``iso``; shutter ``shutterspeed`` (Canon ``1/100``,
  ``0.3``; generic PTP/Nikon ``0.0100s``) or Nikon's ``shutterspeed2`` (``1/100``); aperture is Canon's
  ``aperture`` (``10``) or PTP's ``f-number`` (``f/10``, or a float range). The names present are read
  once from ``--list-config``.
* ``--capture-image-and-download --filename frame.%C`` exposes, downloads and names the file with the
  camera's own suffix (``%C``), e.g. ``frame.cr2``/``frame.NEF``; a RAW+JPEG camera delivers both.
  gphoto2 writes a temporary ``tmpfileXXXXXX`` in its working directory and would ask before
  overwriting, so the driver captures into a fresh folder next to the destination (stdin closed) and
  moves the raw file into place in one rename.

A menu entry counts as the value asked for, and so does the value read back, by ``Camera``'s rule
(within ``readback_tolerance_stops``, 1/6 stop, of exposure). Every call has a time-out; failures raise
``CameraError`` naming the command and gphoto2's message.
"""

from __future__ import annotations

import logging
import os
import re
import shlex
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from .devices import Camera, CameraError, format_shutter_s, show_setting
from .rig import CameraConfig

log = logging.getLogger(__name__)

__all__ = ["GPhotoCamera", "RAW_SUFFIXES", "detect_cameras", "format_shutter_s", "parse_aperture_f", "parse_shutter_s"]

RAW_SUFFIXES = (".3fr", ".arw", ".cr2", ".cr3", ".crw", ".dng", ".erf", ".iiq", ".mos", ".mrw", ".nef",
                ".nrw", ".orf", ".pef", ".raf", ".rw2", ".sr2", ".srf", ".srw", ".x3f")
_CONFIG_NAMES = {
    "iso": ("iso", "isospeed"),
    "shutter": ("shutterspeed", "shutterspeed2", "eos-shutterspeed"),
    "aperture": ("aperture", "f-number", "eos-aperture"),
}


def parse_shutter_s(text: str) -> Optional[float]:
    """Shutter time in seconds of a camera value: ``1/100`` → 0.01, ``0.3``, ``2``, ``1 1/3``,
    ``0.0100s``, ``2"``; None for ``bulb``, ``Time``, ``auto`` and anything else."""
    t = text.strip().rstrip('s"').strip()
    if m := re.fullmatch(r"(\d+)\s+(\d+)/(\d+)", t):
        a, b, c = (int(g) for g in m.groups())
        return a + b / c if c else None
    if m := re.fullmatch(r"(\d+(?:\.\d*)?)/(\d+(?:\.\d*)?)", t):
        num, den = float(m.group(1)), float(m.group(2))
        return num / den if num > 0 and den > 0 else None
    if re.fullmatch(r"\d+(?:\.\d*)?|\.\d+", t):
        value = float(t)
        return value if value > 0 else None
    return None


def parse_aperture_f(text: str) -> Optional[float]:
    """f-number of a camera value: ``f/10``, ``F10``, ``10``, ``5.6`` → float; None otherwise."""
    t = re.sub(r"^[fF]/?", "", text.strip())
    if re.fullmatch(r"\d+(?:\.\d*)?", t) and float(t) > 0:
        return float(t)
    return None


def _parse_iso(text: str) -> Optional[float]:
    t = text.strip()
    return float(t) if re.fullmatch(r"\d+(?:\.\d*)?", t) and float(t) > 0 else None


_PARSERS = {"iso": _parse_iso, "shutter": parse_shutter_s, "aperture": parse_aperture_f}


@dataclass(frozen=True)
class _Widget:
    current: str
    choices: tuple[str, ...]


def _run_gphoto2(executable: str, args: list[str], timeout_s: float, cwd: Optional[Path] = None) -> str:
    """Run gphoto2 under the C locale; its stdout, or ``CameraError`` naming the command."""
    cmd = [executable, *args]
    shown = shlex.join(cmd)
    log.debug("camera: %s", shown)
    try:
        proc = subprocess.run(
            cmd, capture_output=True, text=True, timeout=timeout_s, cwd=cwd, stdin=subprocess.DEVNULL,
            env={**os.environ, "LC_ALL": "C", "LANG": "C"},
        )
    except FileNotFoundError:
        raise CameraError(
            f"camera: the gphoto2 command {executable!r} was not found; install gphoto2 (e.g. "
            f"`apt install gphoto2`) or put it on PATH"
        ) from None
    except subprocess.TimeoutExpired:
        raise CameraError(
            f"camera: `{shown}` did not finish within {timeout_s:g} s (camera busy, asleep or disconnected?)"
        ) from None
    stderr = " ".join(line.strip() for line in proc.stderr.splitlines() if line.strip() and "*** Error" not in line)
    if proc.returncode != 0 or "*** Error" in proc.stderr:
        raise CameraError(f"camera: `{shown}` failed (exit {proc.returncode}): {stderr[:600] or 'no message'}")
    return proc.stdout


def detect_cameras(executable: str = "gphoto2", timeout_s: float = 20.0) -> list[tuple[str, str]]:
    """(model, port) of every camera ``gphoto2 --auto-detect`` lists."""
    out = _run_gphoto2(executable, ["--auto-detect"], timeout_s)
    lines = out.splitlines()
    dashes = next((i for i, line in enumerate(lines) if line.strip() and set(line.strip()) == {"-"}), None)
    found = []
    for line in lines[dashes + 1 if dashes is not None else 0:]:
        parts = line.rstrip().rsplit(None, 1)
        if len(parts) == 2 and parts[0].strip() != "Model":
            found.append((parts[0].strip(), parts[1]))
    specific = {model for model, port in found if port != "usb:"}
    return [(m, p) for m, p in found if not (p == "usb:" and m in specific)]


class GPhotoCamera(Camera):
    """A camera reached through the ``gphoto2`` command.

    ``timeout_s`` bounds every call but the capture, which ``capture_timeout_s`` bounds (exposure,
    flash recharge and download of a raw file). ``executable`` is the gphoto2 program to run. Closing
    releases nothing: every gphoto2 call opens and closes the camera itself.
    """

    def __init__(
        self,
        config: Optional[CameraConfig] = None,
        *,
        executable: str = "gphoto2",
        timeout_s: float = 20.0,
        capture_timeout_s: float = 60.0,
    ) -> None:
        config = config or CameraConfig()
        if not timeout_s > 0 or not capture_timeout_s > 0:
            raise ValueError(f"timeouts must be > 0 s, got timeout_s={timeout_s}, capture_timeout_s={capture_timeout_s}")
        self.executable = executable
        self.timeout_s = float(timeout_s)
        self.capture_timeout_s = float(capture_timeout_s)
        self.model, self.port = self._choose(config, detect_cameras(executable, self.timeout_s))
        self.name = f"camera {self.model}"
        self._names: Optional[dict[str, str]] = None

    @staticmethod
    def _choose(config: CameraConfig, cameras: list[tuple[str, str]]) -> tuple[str, str]:
        wanted = []
        if config.model:
            wanted.append(f"model {config.model!r}")
        if config.port:
            wanted.append(f"port {config.port!r}")
        candidates = [c for c in cameras if not config.port or c[1] == config.port]
        if config.model:
            key = " ".join(config.model.split()).casefold()
            exact = [c for c in candidates if " ".join(c[0].split()).casefold() == key]
            candidates = exact or [c for c in candidates if key in c[0].casefold()]
        listed = "; ".join(f"{m} at {p}" for m, p in cameras) or "none"
        if not candidates:
            raise CameraError(
                f"camera: no camera {'with ' + ' and '.join(wanted) + ' ' if wanted else ''}found by "
                f"`gphoto2 --auto-detect` (cameras found: {listed}); check the USB cable and that the camera "
                f"is on, and that no other program (e.g. a desktop photo importer) holds it"
            )
        if len(candidates) > 1:
            raise CameraError(
                f"camera: {len(candidates)} cameras match ({'; '.join(f'{m} at {p}' for m, p in candidates)}); "
                f"set camera.model or camera.port in the rig config to choose one"
            )
        return candidates[0]

    # --- Camera ---------------------------------------------------------------------------------

    def identify(self) -> str:
        """``model at port``, with the serial number where the camera reports one."""
        serial = ""
        if "serialnumber" in self._config_paths():
            serial = self._get("serialnumber").current
        return f"{self.model} at {self.port}" + (f", serial {serial}" if serial else "")

    def capture(self, destination: Path) -> Path:
        """Expose one frame, download its raw file and move it to ``destination`` with the camera's
        raw suffix (``.CR2``, ``.NEF``, ``.DNG`` …); the path written."""
        destination = Path(destination)
        destination.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=".gphoto2-", dir=destination.parent))
        try:
            self._call(["--capture-image-and-download", "--filename", "frame.%C"], self.capture_timeout_s, cwd=work)
            files = sorted(p.name for p in work.iterdir() if p.is_file() and not p.name.startswith("tmpfile"))
            raws = [name for name in files if Path(name).suffix.lower() in RAW_SUFFIXES]
            if len(raws) != 1:
                raise CameraError(
                    f"camera {self.model} at {self.port}: expected one raw file from the capture, got "
                    f"{', '.join(files) or 'no file'}; set the camera's image format to RAW (or RAW+JPEG)"
                )
            raw = work / raws[0]
            if raw.stat().st_size == 0:
                raise CameraError(f"camera {self.model} at {self.port}: the downloaded raw file {raw.name} is empty")
            final = destination.with_suffix(raw.suffix)
            os.replace(raw, final)
            return final
        finally:
            shutil.rmtree(work, ignore_errors=True)

    # --- settings -------------------------------------------------------------------------------

    def _set(self, setting: str, value: float) -> tuple[Optional[float], str]:
        """Set the menu entry that counts as ``value`` (or, without a menu, its text) unless it is
        current; the value ``--get-config`` reports then."""
        name = self._config_name(setting)
        parse = _PARSERS[setting]
        widget = self._get(name)
        if widget.choices:
            offered = [(c, v) for c in widget.choices if (v := parse(c)) is not None]
            best = self._nearest(setting, value, [v for _, v in offered])
            if best is None:
                raise CameraError(
                    f"{self.name}: {setting} {show_setting(setting, value)} is not among its values for "
                    f"{name!r} ({', '.join(widget.choices)})"
                )
            text = offered[best][0]
        else:
            text = format_shutter_s(value) if setting == "shutter" else f"{value:g}"
        if widget.current != text:
            self._call(["--set-config-value", f"{name}={text}"], self.timeout_s)
        current = self._get(name).current
        return parse(current), (
            f"{current!r} after setting {name}={text} (a value it does not accept in its current mode is "
            f"ignored; set the mode dial to M)"
        )

    def _config_paths(self) -> dict[str, str]:
        """Leaf name → full path of every configuration entry (``--list-config``, read once)."""
        if self._names is None:
            out = self._call(["--list-config"], self.timeout_s)
            paths = [line.strip() for line in out.splitlines() if line.strip().startswith("/")]
            self._names = {path.rsplit("/", 1)[-1]: path for path in paths}
        return self._names

    def _config_name(self, setting: str) -> str:
        paths = self._config_paths()
        for name in _CONFIG_NAMES[setting]:
            if name in paths:
                return name
        raise CameraError(
            f"camera {self.model}: no {setting} setting among its configuration entries "
            f"(looked for {', '.join(_CONFIG_NAMES[setting])})"
        )

    def _get(self, name: str) -> _Widget:
        out = self._call(["--get-config", name], self.timeout_s)
        current = None
        choices = []
        for line in out.splitlines():
            key, _, rest = line.partition(":")
            if key.strip() == "Current":
                current = rest.strip()
            elif key.strip() == "Choice":
                index_and_value = rest.split(None, 1)
                if len(index_and_value) == 2:
                    choices.append(index_and_value[1].strip())
        if current is None:
            raise CameraError(f"camera {self.model}: `gphoto2 --get-config {name}` printed no 'Current:' line")
        return _Widget(current, tuple(choices))

    def _call(self, args: list[str], timeout_s: float, cwd: Optional[Path] = None) -> str:
        return _run_gphoto2(self.executable, ["--camera", self.model, "--port", self.port, *args], timeout_s, cwd)
